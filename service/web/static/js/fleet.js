// The fleet view: every vehicle in a virtualised table (only the visible rows exist in the DOM), the latched
// alarms and the replicas' bucket ownership changes. Rows arrive as deltas a few times a second; rendering is
// coalesced into one animation frame.

import { AlarmList } from './alarms.js';
import { LEVELS, LEVEL_RANK, age, el, fixed } from './format.js';
import { OwnershipList } from './ownership.js';

const OVERSCAN_ROWS = 6;

const COMPARE = {
  id: (a, b) => (a.id < b.id ? -1 : a.id > b.id ? 1 : 0),
  level: (a, b) => LEVEL_RANK[a.level] - LEVEL_RANK[b.level],
  profile: (a, b) => a.profile.localeCompare(b.profile),
  seen: (a, b) => (a.seen ?? -Infinity) - (b.seen ?? -Infinity),
  vx: (a, b) => (a.vx ?? -Infinity) - (b.vx ?? -Infinity),
  tf: (a, b) => Math.abs(a.tf ?? 0) - Math.abs(b.tf ?? 0),
  sf: (a, b) => Math.abs(a.sf ?? 0) - Math.abs(b.sf ?? 0),
  load: (a, b) => (a.load ?? -Infinity) - (b.load ?? -Infinity),
  alarms: null, // set per render from the alarm counts
};

export class FleetView {
  /** @param {import('./alarms.js').AlarmStore} alarms */
  constructor(alarms, onUnauthorized) {
    this.alarms = alarms;
    this.rows = new Map();
    this.order = [];
    this.orderDirty = true;
    this.levels = new Set();
    this.text = '';
    this.sort = { key: 'level', descending: true };
    this.serverOffsetS = 0;
    this.updatedAt = null;
    this.frame = 0;
    this.pool = [];
    this.table = document.getElementById('fleet-table');
    this.body = document.getElementById('fleet-body');
    this.spacer = document.getElementById('fleet-spacer');
    this.foot = document.getElementById('fleet-foot');
    this.filters = document.getElementById('level-filters');
    this.rowHeight = 34;
    this.alarmList = new AlarmList(document.getElementById('fleet-alarms'), alarms, {
      empty: document.getElementById('alarms-empty'),
      onUnauthorized,
    });
    this.ownership = new OwnershipList(
      document.getElementById('ownership-box'),
      document.getElementById('ownership-list'),
    );
    alarms.subscribe(() => {
      this.orderDirty = this.orderDirty || this.sort.key === 'alarms';
      this.schedule();
    });
    this.buildFilters();
    this.body.addEventListener('scroll', () => this.schedule(), { passive: true });
    new ResizeObserver(() => this.schedule()).observe(this.body);
    document.getElementById('fleet-search').addEventListener('input', (event) => {
      this.text = event.target.value.trim().toLowerCase();
      this.orderDirty = true;
      this.schedule();
    });
    for (const header of this.table.querySelectorAll('[data-sort]')) {
      header.querySelector('button').addEventListener('click', () => this.sortBy(header.dataset.sort));
    }
    this.updateSortHeaders();
    setInterval(() => this.schedule(), 1000); // ages
  }

  buildFilters() {
    this.filterButtons = new Map();
    const all = el('button', { type: 'button', 'aria-pressed': 'true', 'data-level': 'ALL' }, 'All');
    all.addEventListener('click', () => {
      this.levels.clear();
      this.orderDirty = true;
      this.schedule();
    });
    this.filterButtons.set('ALL', all);
    this.filters.append(all);
    for (const level of LEVELS) {
      const button = el('button', { type: 'button', 'aria-pressed': 'false', 'data-level': level }, level);
      button.addEventListener('click', () => {
        if (this.levels.has(level)) this.levels.delete(level);
        else this.levels.add(level);
        this.orderDirty = true;
        this.schedule();
      });
      this.filterButtons.set(level, button);
      this.filters.append(button);
    }
  }

  sortBy(key) {
    if (this.sort.key === key) this.sort.descending = !this.sort.descending;
    else this.sort = { key, descending: ['level', 'tf', 'sf', 'load', 'alarms', 'seen'].includes(key) };
    this.updateSortHeaders();
    this.orderDirty = true;
    this.schedule();
  }

  updateSortHeaders() {
    for (const header of this.table.querySelectorAll('[data-sort]')) {
      const active = header.dataset.sort === this.sort.key;
      if (active) header.setAttribute('aria-sort', this.sort.descending ? 'descending' : 'ascending');
      else header.removeAttribute('aria-sort');
    }
  }

  /** A "fleet" frame: all rows ({full: true}) or the rows that changed. */
  apply(frame, columns) {
    const started = performance.now();
    this.serverOffsetS = frame.now_s - Date.now() / 1000;
    if (frame.full) this.rows.clear();
    for (const values of frame.rows) {
      const row = {};
      columns.forEach((name, i) => {
        row[name] = values[i];
      });
      this.rows.set(row.id, {
        id: row.id,
        profile: row.profile,
        level: row.level,
        seen: row.last_seen_s,
        vx: row.vx,
        tf: row.torque_fault,
        sf: row.steer_fault,
        alive: row.alive,
        load: row.payload_kg ?? null,
      });
    }
    for (const id of frame.removed || []) this.rows.delete(id);
    this.updatedAt = new Date();
    this.orderDirty = true;
    performance.measure('fleet-apply', { start: started, end: performance.now() });
    this.schedule();
  }

  /** An "ownership" frame of a stream from ``replica``. */
  onOwnership(frame, replica) {
    this.ownership.apply(frame, replica);
  }

  clear() {
    this.ownership.clear();
    this.rows.clear();
    this.orderDirty = true;
    this.schedule();
  }

  schedule() {
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      if (!this.table.closest('.view').hidden) this.render();
    });
  }

  computeOrder() {
    const counts = this.alarms.countByVehicle();
    const perLevel = { FAULT: 0, WARN: 0, STALE: 0, OK: 0 };
    const shown = [];
    for (const row of this.rows.values()) {
      perLevel[row.level] += 1;
      row.alarms = counts.get(row.id) || 0;
      if (this.levels.size && !this.levels.has(row.level)) continue;
      if (this.text && !row.id.toLowerCase().includes(this.text) && !row.profile.toLowerCase().includes(this.text)) {
        continue;
      }
      shown.push(row);
    }
    const compare = this.sort.key === 'alarms' ? (a, b) => a.alarms - b.alarms : COMPARE[this.sort.key];
    const sign = this.sort.descending ? -1 : 1;
    shown.sort((a, b) => sign * compare(a, b) || COMPARE.id(a, b));
    this.order = shown;
    this.orderDirty = false;
    this.filterButtons.get('ALL').textContent = `All ${this.rows.size}`;
    this.filterButtons.get('ALL').setAttribute('aria-pressed', String(this.levels.size === 0));
    for (const level of LEVELS) {
      const button = this.filterButtons.get(level);
      button.textContent = `${level} ${perLevel[level]}`;
      button.setAttribute('aria-pressed', String(this.levels.has(level)));
    }
    this.table.setAttribute('aria-rowcount', String(shown.length + 1));
    this.table.dataset.total = String(this.rows.size);
    this.table.dataset.shown = String(shown.length);
    this.spacer.style.height = `${shown.length * this.rowHeight}px`;
  }

  render() {
    const started = performance.now();
    if (this.orderDirty) this.computeOrder();
    const top = this.body.scrollTop;
    const height = this.body.clientHeight;
    const first = Math.max(0, Math.floor(top / this.rowHeight) - OVERSCAN_ROWS);
    const last = Math.min(this.order.length, Math.ceil((top + height) / this.rowHeight) + OVERSCAN_ROWS);
    const needed = Math.max(0, last - first);
    while (this.pool.length < needed) {
      const row = this.createRow();
      this.pool.push(row);
      this.body.append(row.node);
    }
    const nowS = Date.now() / 1000 + this.serverOffsetS;
    for (let k = 0; k < this.pool.length; k += 1) {
      const row = this.pool[k];
      if (k >= needed) {
        row.node.hidden = true;
        continue;
      }
      const index = first + k;
      row.node.hidden = false;
      row.node.style.transform = `translateY(${index * this.rowHeight}px)`;
      row.node.setAttribute('aria-rowindex', String(index + 2));
      this.fillRow(row, this.order[index], nowS);
    }
    const shown = this.order.length;
    const updated = this.updatedAt ? ` · updated ${this.updatedAt.toLocaleTimeString([], { hour12: false })}` : '';
    this.foot.textContent = `${shown} of ${this.rows.size} vehicles shown${updated}`;
    performance.measure('fleet-render', { start: started, end: performance.now() });
  }

  createRow() {
    const cells = {};
    const node = el('div', { class: 'vrow', role: 'row' });
    for (const name of ['id', 'level', 'profile', 'seen', 'vx', 'tf', 'sf', 'load', 'alarms']) {
      const numeric = ['vx', 'tf', 'sf', 'load', 'alarms'].includes(name);
      cells[name] = el('span', { role: 'cell', class: numeric ? 'num' : undefined });
      node.append(cells[name]);
    }
    const link = el('a');
    cells.id.append(link);
    const badge = el('span', { class: 'level' });
    cells.level.append(badge);
    return { node, cells, link, badge, shown: {} };
  }

  fillRow(row, data, nowS) {
    const text = {
      seen: data.seen === null ? 'never' : age(nowS - data.seen),
      vx: fixed(data.vx, 2),
      tf: fixed(data.tf, 1),
      sf: fixed(data.sf, 4),
      load: data.load > 0 ? fixed(data.load, 0) : '–',
      alarms: data.alarms ? String(data.alarms) : '',
      profile: data.profile,
    };
    if (row.shown.id !== data.id) {
      row.link.textContent = data.id;
      row.link.href = `#/vehicle/${encodeURIComponent(data.id)}`;
      row.node.dataset.vehicle = data.id;
      row.shown.id = data.id;
    }
    if (row.shown.level !== data.level) {
      row.badge.textContent = data.level;
      row.badge.className = `level level-${data.level}`;
      row.node.className = `vrow level-row-${data.level}`;
      row.node.dataset.level = data.level;
      row.shown.level = data.level;
    }
    for (const [name, value] of Object.entries(text)) {
      if (row.shown[name] !== value) {
        row.cells[name].textContent = value;
        row.shown[name] = value;
      }
    }
  }
}
