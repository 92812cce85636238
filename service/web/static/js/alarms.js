// Latched alarms: a store fed by the stream's "alarms" frames, and a list with acknowledge buttons.

import { api } from './api.js';
import { ALARM_KINDS, LEVEL_RANK, clock, el, levelBadge } from './format.js';

const MAX_SHOWN = 100;

export class AlarmStore {
  constructor() {
    this.alarms = new Map();
    this.listeners = new Set();
  }

  /** A frame {full, upsert: [record], remove: [id]} from the stream. */
  apply(frame) {
    if (frame.full) this.alarms.clear();
    for (const record of frame.upsert || []) this.alarms.set(record.id, record);
    for (const id of frame.remove || []) this.alarms.delete(id);
    this.emit();
  }

  /** A record answered by the API (after an acknowledgement). */
  upsert(record) {
    if (record.latched === false) this.alarms.delete(record.id);
    else this.alarms.set(record.id, record);
    this.emit();
  }

  /** Unacknowledged first, then raised before cleared, then the most severe, then the newest. */
  sorted(vehicle = null) {
    const list = [...this.alarms.values()].filter((a) => vehicle === null || a.vehicle === vehicle);
    return list.sort(
      (a, b) =>
        Number(a.acknowledged) - Number(b.acknowledged) ||
        Number(a.state !== 'raised') - Number(b.state !== 'raised') ||
        LEVEL_RANK[b.level] - LEVEL_RANK[a.level] ||
        b.updated_t_ns - a.updated_t_ns,
    );
  }

  /** Latched alarms per vehicle. */
  countByVehicle() {
    const counts = new Map();
    for (const a of this.alarms.values()) counts.set(a.vehicle, (counts.get(a.vehicle) || 0) + 1);
    return counts;
  }

  subscribe(listener) {
    this.listeners.add(listener);
    return () => this.listeners.delete(listener);
  }

  emit() {
    for (const listener of this.listeners) listener();
  }
}

// Alarms on the estimates: the dashboard links the estimate history around them.
const HISTORY_KINDS = new Set(['torque_fault', 'steer_fault', 'torque_effectiveness', 'steer_effectiveness', 'out_of_domain']);

function describeValue(alarm) {
  if (alarm.value === null || alarm.value === undefined) return null;
  const digits = alarm.kind === 'steer_fault' ? 4 : alarm.kind === 'torque_fault' ? 1 : alarm.kind.endsWith('_effectiveness') ? 3 : 2;
  const unit = alarm.kind === 'steer_fault' ? ' rad' : alarm.kind === 'torque_fault' ? ' N m' : '';
  const threshold = alarm.threshold === null ? '' : ` (threshold ${Number(alarm.threshold).toFixed(digits)}${unit})`;
  return `value ${Number(alarm.value).toFixed(digits)}${unit}${threshold}`;
}

export class AlarmList {
  /**
   * @param {HTMLUListElement} list
   * @param {AlarmStore} store
   * @param {{vehicle?: string|null, empty?: HTMLElement, box?: HTMLElement, onUnauthorized?: () => void,
   *          onLookBack?: ((alarm: object) => void)|null}} options  onLookBack: a "Look back" button on each alarm
   *          on the estimates, which calls it with the alarm's record
   */
  constructor(list, store, { vehicle = null, empty = null, box = null, onUnauthorized = () => {}, onLookBack = null } = {}) {
    this.list = list;
    this.store = store;
    this.vehicle = vehicle;
    this.empty = empty;
    this.box = box;
    this.onUnauthorized = onUnauthorized;
    this.onLookBack = onLookBack;
    this.items = new Map();
    this.errors = new Map();
    this.more = null;
    this.unsubscribe = store.subscribe(() => this.render());
    this.render();
  }

  close() {
    this.unsubscribe();
  }

  render() {
    const all = this.store.sorted(this.vehicle);
    const alarms = all.slice(0, MAX_SHOWN);
    if (!this.more) {
      this.more = el('p', { class: 'hint alarm-more' });
      this.list.after(this.more);
    }
    this.more.hidden = all.length <= MAX_SHOWN;
    this.more.textContent = `and ${all.length - MAX_SHOWN} more, less urgent`;
    const wanted = new Set(alarms.map((a) => a.id));
    for (const [id, item] of this.items) {
      if (!wanted.has(id)) {
        item.remove();
        this.items.delete(id);
      }
    }
    alarms.forEach((alarm, index) => {
      let item = this.items.get(alarm.id);
      if (!item) {
        item = this.create(alarm);
        this.items.set(alarm.id, item);
      }
      this.update(item, alarm);
      if (this.list.children[index] !== item) this.list.insertBefore(item, this.list.children[index] || null);
    });
    if (this.empty) this.empty.hidden = alarms.length > 0;
    if (this.box) this.box.hidden = alarms.length === 0;
  }

  create(alarm) {
    const button = el('button', { type: 'button', class: 'ack' }, 'Acknowledge');
    button.addEventListener('click', () => this.acknowledge(alarm.id, button));
    return el(
      'li',
      { class: 'alarm', 'data-alarm-id': alarm.id },
      el('span', { class: 'alarm-title' }),
      el('div', { class: 'alarm-actions' }, button),
      el('span', { class: 'alarm-state' }),
      el('span', { class: 'alarm-message' }),
      el('span', { class: 'alarm-meta' }),
      el('p', { class: 'alarm-error', role: 'alert' }),
    );
  }

  update(item, alarm) {
    item.dataset.level = alarm.level;
    item.dataset.state = alarm.state;
    item.dataset.acknowledged = String(alarm.acknowledged);
    item.dataset.vehicle = alarm.vehicle;
    item.dataset.kind = alarm.kind;
    const title = item.querySelector('.alarm-title');
    const kind = ALARM_KINDS[alarm.kind] || alarm.kind;
    title.replaceChildren(
      levelBadge(alarm.level),
      ` ${kind} · `,
      el('a', { href: `#/vehicle/${encodeURIComponent(alarm.vehicle)}` }, alarm.vehicle),
    );
    item.querySelector('.alarm-message').textContent = alarm.message;
    const meta = [describeValue(alarm), `raised ${clock(alarm.raised_t_ns)}`];
    if (alarm.occurrences > 1) meta.push(`${alarm.occurrences} times`);
    if (alarm.acknowledged) meta.push(`acknowledged ${clock(alarm.acknowledged_t_ns)}`);
    item.querySelector('.alarm-meta').textContent = meta.filter(Boolean).join(' · ');
    const state = `${alarm.state === 'raised' ? 'active' : 'cleared'} · ${
      alarm.acknowledged ? 'acknowledged' : 'unacknowledged'
    }`;
    item.querySelector('.alarm-state').textContent = state;
    const button = item.querySelector('button.ack');
    button.hidden = alarm.acknowledged;
    button.setAttribute('aria-label', `Acknowledge ${kind.toLowerCase()} of ${alarm.vehicle}`);
    item.querySelector('.alarm-error').textContent = this.errors.get(alarm.id) || '';
    const actions = item.querySelector('.alarm-actions');
    if (HISTORY_KINDS.has(alarm.kind) && !actions.querySelector('a.around')) {
      // the vehicle's estimates 30 s either side of the alarm, from the estimate history (vehicle clock)
      const at = alarm.raised_t_ns / 1e9;
      const query = `start=${(at - 30).toFixed(3)}&end=${(at + 30).toFixed(3)}&format=csv`;
      const href = `/vehicles/${encodeURIComponent(alarm.vehicle)}/estimates?${query}`;
      actions.prepend(el('a', { class: 'around', href, download: '' }, 'Estimates ±30 s (CSV)'));
      if (this.onLookBack) {
        const button = el('button', { type: 'button', class: 'look-back' }, 'Look back');
        button.setAttribute('aria-label', `Look back at the estimates around the ${kind.toLowerCase()} of ${alarm.vehicle}`);
        button.addEventListener('click', () => this.onLookBack(this.store.alarms.get(alarm.id) || alarm));
        actions.prepend(button);
      }
    }
  }

  async acknowledge(id, button) {
    button.disabled = true;
    this.errors.delete(id);
    try {
      const record = await api('POST', `/alarms/${encodeURIComponent(id)}/ack`, { by: 'dashboard' });
      this.store.upsert(record);
    } catch (err) {
      this.errors.set(id, `Not acknowledged: ${err.message}`);
      this.render();
      if (err.status === 401) this.onUnauthorized();
    } finally {
      button.disabled = false;
    }
  }
}
