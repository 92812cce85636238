// The profiles view: each profile's parameters and bounds, its active gains and their certificate, and a form
// that changes parameters or bounds (PUT /profiles/{name}) or designs the gains again (POST .../synthesis),
// following the synthesis job until it succeeds or says why it failed.

import { api } from './api.js';
import { el, shortHash } from './format.js';

const JOB_POLL_MS = 500;
const FINAL = new Set(['succeeded', 'failed', 'superseded', 'interrupted']);

function number(value, digits = 6) {
  if (value === null || value === undefined) return '–';
  if (typeof value !== 'number') return String(value);
  if (value !== 0 && (Math.abs(value) < 1e-3 || Math.abs(value) >= 1e6)) return value.toExponential(3);
  return String(Number(value.toPrecision(digits)));
}

function certificateRows(gains) {
  const c = gains.certificate;
  const where = c.spectral_radius_at || {};
  const whereText = Object.entries(where)
    .map(([k, v]) => `${k} = ${number(v, 4)}`)
    .join(', ');
  const timings = c.timings_s || {};
  const total = timings.total_s ?? Object.values(timings).reduce((s, v) => s + (Number.isFinite(v) ? v : 0), 0);
  const rows = [
    ['Verified', el('span', { class: c.verified ? 'verified-yes' : 'verified-no' }, c.verified ? 'yes' : 'no')],
    ['Version', el('code', {}, gains.version)],
    ['Design', `${c.design}, fault order ${c.fault_order}, ${c.lyapunov} P, ${c.lmi_form} LMIs`],
    ['Decay rate', `${number(c.decay_rate)} (certified; requested ${number(c.requested_decay_rate)})`],
    ['Spectral radius', `${number(c.spectral_radius_max)} max over ${c.grid_points} grid points${whereText ? ` (at ${whereText})` : ''}`],
    ['LMI min eigenvalue', `${number(c.lmi_min_eigenvalue)} (margin ${number(c.margin)}; ${c.n_lmis_verified} LMIs checked)`],
  ];
  for (const [name, value] of Object.entries(c.performance || {})) rows.push([`Bound: ${name}`, number(value)]);
  rows.push(
    ['Solver', `${c.solver} ${c.solver_version}, ${c.solver_status}${c.solver_iterations ? `, ${c.solver_iterations} iterations` : ''}, ${c.solves} solve(s)`],
    ['Synthesis time', `${number(total, 3)} s`],
    ['Content hash', el('code', {}, shortHash(c.content_hash))],
  );
  for (const note of c.notes || []) rows.push(['Note', note]);
  return rows;
}

function kv(rows) {
  return el('dl', { class: 'kv' }, ...rows.flatMap(([k, v]) => [el('dt', {}, k), el('dd', {}, v)]));
}

export class ProfilesView {
  constructor(onUnauthorized) {
    this.root = document.getElementById('profiles');
    this.onUnauthorized = onUnauthorized;
    this.active = false;
    this.polls = new Map();
  }

  async enter() {
    this.active = true;
    await this.load();
  }

  leave() {
    this.active = false;
    for (const timer of this.polls.values()) clearTimeout(timer);
    this.polls.clear();
  }

  async load() {
    let profiles;
    try {
      profiles = await api('GET', '/profiles');
    } catch (err) {
      this.root.replaceChildren(el('p', { class: 'errors', role: 'alert' }, `Cannot load the profiles: ${err.message}`));
      if (err.status === 401) this.onUnauthorized();
      return;
    }
    const cards = await Promise.all(profiles.map((profile) => this.card(profile)));
    if (!this.active) return;
    this.root.replaceChildren(...cards);
    for (const profile of profiles) {
      if (profile.pending_job) this.follow(profile.name, profile.pending_job);
    }
  }

  // A stored profile the service could not load at start-up: it does not run; say why.
  failedCard(profile) {
    return el(
      'article',
      { class: 'panel profile', 'data-profile': profile.name, 'data-state': 'failed' },
      el('div', { class: 'profile-head' }, el('h2', {}, profile.name), el('span', {}, 'not running')),
      el(
        'p',
        { class: 'errors', role: 'alert' },
        `This stored profile could not be loaded at start-up and does not run: ${profile.error} ` +
          `A valid PUT /profiles/${profile.name} replaces it.`,
      ),
    );
  }

  async card(profile) {
    if (profile.state === 'failed') return this.failedCard(profile);
    const name = encodeURIComponent(profile.name);
    const [gains, form] = await Promise.all([
      api('GET', `/profiles/${name}/gains`).catch(() => null),
      api('GET', `/ui/profiles/${name}/form`),
    ]);
    const versions = el(
      'ul',
      { class: 'versions', 'aria-label': 'Stored gain versions, oldest first' },
      ...profile.gain_versions.map((v) =>
        el('li', { class: v === profile.active_version ? 'active' : undefined, title: v }, shortHash(v)),
      ),
    );
    const certificate = gains
      ? kv(certificateRows(gains))
      : el('p', { class: 'hint' }, 'No active gains yet: the first design is running or has failed (see below).');
    const job = el('div', { class: 'job', role: 'status', 'aria-live': 'polite', hidden: true });
    const card = el(
      'article',
      { class: 'panel profile', 'data-profile': profile.name, 'data-active-version': profile.active_version || '' },
      el(
        'div',
        { class: 'profile-head' },
        el('h2', {}, profile.name),
        el('span', { class: 'hint' }, profile.spec.description || ''),
        el('span', {}, `${profile.vehicles} vehicle${profile.vehicles === 1 ? '' : 's'}`),
      ),
      el(
        'div',
        { class: 'profile-grid' },
        el(
          'section',
          { 'aria-label': `Active gains of ${profile.name}` },
          el('h3', {}, 'Active gains and certificate'),
          certificate,
          el('h3', {}, 'Gain versions'),
          versions,
        ),
        el(
          'section',
          { 'aria-label': `Parameters and bounds of ${profile.name}` },
          el('h3', {}, 'Parameters and bounds'),
          this.form(profile.name, form, job),
          job,
        ),
      ),
    );
    return card;
  }

  form(name, form, job) {
    const inputs = [];
    const fieldset = (section, legend) =>
      el(
        'fieldset',
        {},
        el('legend', {}, legend),
        el(
          'div',
          { class: 'fields' },
          ...form.fields[section].map((field) => {
            const id = `f-${name}-${section}-${field.name}`;
            const value = form.resolved[section][field.name];
            const boolean = field.kind === 'boolean';
            const input = el('input', {
              id,
              type: boolean ? 'checkbox' : 'number',
              step: boolean ? undefined : 'any',
              required: field.kind === 'number',
              value: boolean || value === null ? undefined : value,
              checked: boolean && value ? true : undefined,
              placeholder: field.kind === 'optional_number' ? 'none' : undefined,
              'data-section': section,
              'data-field': field.name,
              min: field.minimum ?? undefined,
              max: field.maximum ?? undefined,
              'aria-describedby': `${id}-help`,
            });
            const read = () => readField(field.kind, input);
            input.addEventListener(boolean ? 'change' : 'input', () => input.classList.toggle('changed', read() !== value));
            inputs.push({ section, field: field.name, input, value, read });
            return el(
              'div',
              { class: 'field' },
              el('label', { for: id }, el('span', { class: 'field-name' }, field.name)),
              input,
              el('span', { class: 'field-help', id: `${id}-help` }, field.description),
            );
          }),
        ),
      );
    const errors = el('ul', { class: 'errors', role: 'alert' });
    const save = el('button', { type: 'submit', class: 'primary' }, 'Save and design new gains');
    const again = el('button', { type: 'button' }, 'Design again with these values');
    const element = el(
      'form',
      { class: 'spec-form', novalidate: true, 'aria-label': `Change ${name}` },
      fieldset('params', 'Vehicle parameters (Table 1)'),
      fieldset('bounds', 'Operating bounds (eq. 13)'),
      el('div', { class: 'form-actions' }, save, again),
      errors,
    );
    const submit = async (body, method, path) => {
      errors.replaceChildren();
      save.disabled = again.disabled = true;
      try {
        const answer = await api(method, path, body);
        if (answer.job) this.follow(name, answer.job, job);
        else this.showJob(job, { status: 'succeeded', applied: true });
      } catch (err) {
        errors.replaceChildren(...[err.message, ...err.problems].map((text) => el('li', {}, text)));
        if (err.status === 401) this.onUnauthorized();
      } finally {
        save.disabled = again.disabled = false;
      }
    };
    element.addEventListener('submit', (event) => {
      event.preventDefault();
      // Send the spec as stored, with only the fields the operator changed: unset fields keep following the defaults.
      const spec = structuredClone(form.stored);
      let changed = 0;
      for (const { section, field, input, value, read } of inputs) {
        const next = read();
        if (next === value) continue;
        spec[section] = spec[section] || {};
        spec[section][field] = typeof next === 'number' && !Number.isFinite(next) ? input.value : next;
        changed += 1;
      }
      if (!changed) {
        errors.replaceChildren(el('li', {}, 'Nothing changed. Use "Design again" to redesign with the same values.'));
        return;
      }
      submit(spec, 'PUT', `/profiles/${encodeURIComponent(name)}`);
    });
    again.addEventListener('click', () => submit(undefined, 'POST', `/profiles/${encodeURIComponent(name)}/synthesis`));
    return element;
  }

  /** Poll a job until it ends, showing its progress in the profile's job box; reload the profiles at the end. */
  follow(name, jobId, box = null) {
    clearTimeout(this.polls.get(name));
    const poll = async () => {
      if (!this.active) return;
      const target = box || this.root.querySelector(`[data-profile="${CSS.escape(name)}"] .job`);
      let job;
      try {
        job = await api('GET', `/jobs/${encodeURIComponent(jobId)}`);
      } catch (err) {
        if (target) this.showJob(target, { status: 'error', id: jobId, reason: err.message });
        return;
      }
      if (target) this.showJob(target, job);
      if (FINAL.has(job.status)) {
        this.polls.delete(name);
        if (job.status === 'succeeded') {
          await this.load();
          const fresh = this.root.querySelector(`[data-profile="${CSS.escape(name)}"] .job`);
          if (fresh) this.showJob(fresh, job);
        }
        return;
      }
      this.polls.set(name, setTimeout(poll, JOB_POLL_MS));
    };
    poll();
  }

  showJob(box, job) {
    box.hidden = false;
    box.dataset.status = job.status;
    box.dataset.job = job.id || '';
    const lines = [];
    if (job.applied) {
      lines.push('Applied: only thresholds or limits changed, no new design needed.');
    } else if (job.status === 'queued') {
      lines.push(`Job ${job.id}: queued behind the running design.`);
    } else if (job.status === 'running') {
      const seconds = job.started_t_ns ? (Date.now() * 1e6 - job.started_t_ns) / 1e9 : 0;
      lines.push(`Job ${job.id}: designing and certifying new gains… ${Math.max(0, seconds).toFixed(1)} s`);
    } else if (job.status === 'succeeded') {
      const c = job.certificate || {};
      lines.push(`Job ${job.id} succeeded in ${number(job.duration_s, 3)} s: gain version `);
      lines.push(el('code', { class: 'new-version' }, job.gain_version));
      lines.push(` is active (verified: ${c.verified ? 'yes' : 'no'}, decay rate ${number(c.decay_rate)}).`);
    } else if (job.status === 'error') {
      lines.push(`Cannot follow job ${job.id}: ${job.reason}`);
    } else {
      lines.push(`Job ${job.id} ${job.status}${job.error ? ` (${job.error})` : ''}: ${job.reason || 'no reason given'}. `);
      lines.push('The active gains are unchanged.');
    }
    box.replaceChildren(el('p', {}, ...lines));
  }
}

/** The value an input stands for: a checkbox's state, null for an empty optional number, else the number. */
function readField(kind, input) {
  if (kind === 'boolean') return input.checked;
  if (kind === 'optional_number' && input.value === '') return null;
  return input.value === '' ? NaN : Number(input.value);
}
