// The vehicle view: live uPlot time plots of the last history_s seconds, like the paper's Figs. 4 and 6:
// measured and estimated v_x and r, estimated v_y, the fault estimates with their alarm thresholds, and the
// simulator's ground truth when it publishes one. "Look back" on an alarm shows instead every estimate of the
// same span centred on the alarm, from the estimate history (GET /vehicles/{id}/estimates?start=&end=), until
// "Back to live"; the live stream goes on meanwhile.

import { AlarmList } from './alarms.js';
import { ALARM_KINDS, age, clock, el, fixed, levelBadge, shortHash } from './format.js';
import { api } from './api.js';

const COLOURS = {
  measured: '#6e7781',
  estimated: '#0969da',
  truth: '#bc4c00',
  warn: '#bf8700',
  fault: '#cf222e',
  steering: '#8250df',
};
const PLOT_HEIGHT = 210;
const MIN_REDRAW_MS = 150;

// Each plot: estimate columns from the trace points, truth columns, and thresholds (from the vehicle's profile).
const PLOTS = [
  { key: 'vx', title: 'Longitudinal speed vₓ [m/s]', measured: 'vx_meas', estimated: 'vx', truth: 'vx', digits: 2 },
  { key: 'r', title: 'Yaw rate r [rad/s]', measured: 'r_meas', estimated: 'r', truth: 'r', digits: 4 },
  { key: 'vy', title: 'Lateral speed v_y [m/s] (not measured)', estimated: 'vy', truth: 'vy', digits: 3 },
  {
    key: 'tf',
    title: 'Torque fault T_f [N m]',
    estimated: 'torque_fault',
    truth: 'torque_fault',
    warn: 'torque_warn_nm',
    fault: 'torque_fault_nm',
    digits: 1,
  },
  {
    key: 'sf',
    title: 'Steering fault δ_f [rad]',
    estimated: 'steer_fault',
    truth: 'steer_fault',
    warn: 'steer_warn_rad',
    fault: 'steer_fault_rad',
    digits: 4,
  },
  // Shown only for a profile that runs the loss-of-effectiveness stage (status.effectiveness); alarms below WARN.
  {
    key: 'alpha',
    title: 'Actuator effectiveness α [-] (1: healthy)',
    lines: [
      ['torque_alpha', 'drive torque', COLOURS.estimated],
      ['steer_alpha', 'steering', COLOURS.steering],
    ],
    warn: 'effectiveness_warn',
    fault: 'effectiveness_fault',
    oneSided: true,
    optional: 'effectiveness',
    digits: 3,
  },
];

/** Merge two time-sorted tables on their first column: x and, per x, the row index in each (or -1). */
function mergeByTime(a, b) {
  const x = [];
  const ia = [];
  const ib = [];
  let i = 0;
  let j = 0;
  while (i < a.length || j < b.length) {
    const ta = i < a.length ? a[i][0] : Infinity;
    const tb = j < b.length ? b[j][0] : Infinity;
    if (ta === tb) {
      x.push(ta);
      ia.push(i++);
      ib.push(j++);
    } else if (ta < tb) {
      x.push(ta);
      ia.push(i++);
      ib.push(-1);
    } else {
      x.push(tb);
      ia.push(-1);
      ib.push(j++);
    }
  }
  return { x, ia, ib };
}

/** The road grade the vehicle sends (measurement flag bit 1), in percent (100 tan theta, + uphill). */
function roadGrade(status) {
  if (status.grade_seq === null || status.grade_seq === undefined) return 'not sent';
  const percent = 100 * Math.tan(status.grade_rad);
  const shown = `${percent > 0 ? '+' : ''}${percent.toFixed(1)} %`;
  if (status.grade_seq === status.last_seq) return shown;
  return `not in the latest sample (${shown} at #${status.grade_seq})`;
}

/** Whether the fault alarms judge the vehicle's estimates now, and why not (faults_judged, unjudged_because). */
function judging(status) {
  if (status.faults_judged === null || status.faults_judged === undefined) return 'no estimate yet';
  if (status.faults_judged) return 'judging';
  return `holding the levels: ${status.unjudged_because.join(', ')}`;
}

export class VehicleView {
  constructor(alarms, onUnauthorized) {
    this.alarmsStore = alarms;
    this.onUnauthorized = onUnauthorized;
    this.title = document.getElementById('vehicle-title');
    this.level = document.getElementById('vehicle-level');
    this.facts = document.getElementById('vehicle-facts');
    this.missing = document.getElementById('vehicle-missing');
    this.container = document.getElementById('plots');
    this.lookbackBox = document.getElementById('vehicle-lookback');
    this.lookbackText = document.getElementById('vehicle-lookback-text');
    this.liveButton = document.getElementById('vehicle-live');
    this.liveButton.addEventListener('click', () => this.backToLive());
    this.payloadForm = document.getElementById('payload-form');
    this.payloadInput = document.getElementById('payload-input');
    this.payloadStatus = document.getElementById('payload-status');
    this.payloadForm.addEventListener('submit', (event) => {
      event.preventDefault();
      this.reportPayload();
    });
    this.lookback = null;
    this.lookbackRequest = 0;
    this.plots = [];
    this.vehicle = null;
    this.alarmList = null;
    this.resize = new ResizeObserver(() => this.fit());
    this.resize.observe(this.container);
  }

  enter(vehicle) {
    this.leave();
    this.vehicle = vehicle;
    this.points = [];
    this.truth = [];
    this.status = null;
    this.historyS = 60;
    this.pointColumns = null;
    this.pointNames = null;
    this.truthColumns = null;
    this.lastDraw = 0;
    this.timer = 0;
    this.title.textContent = vehicle;
    this.level.replaceWith((this.level = levelBadge('–')));
    this.level.id = 'vehicle-level';
    this.facts.replaceChildren();
    this.payloadInput.value = '';
    this.showPayloadStatus('', '');
    this.missing.hidden = true;
    this.alarmList = new AlarmList(document.getElementById('vehicle-alarms'), this.alarmsStore, {
      vehicle,
      box: document.getElementById('vehicle-alarms-box'),
      onUnauthorized: this.onUnauthorized,
      onLookBack: (alarm) => this.lookBack(alarm),
    });
    this.showLive();
    this.build();
  }

  leave() {
    for (const plot of this.plots) plot.chart.destroy();
    this.plots = [];
    this.container.replaceChildren();
    if (this.alarmList) {
      this.alarmList.close();
      document.getElementById('vehicle-alarms').replaceChildren();
      this.alarmList = null;
    }
    clearTimeout(this.timer);
    this.vehicle = null;
    this.showLive();
  }

  found() {
    this.missing.hidden = true;
  }

  notFound(detail) {
    this.missing.textContent = `${detail}. It appears here once the service has received its first measurement.`;
    this.missing.hidden = false;
  }

  build() {
    const width = Math.max(320, this.container.clientWidth / (this.container.clientWidth > 1200 ? 2 : 1) - 40);
    for (const spec of PLOTS) {
      const figure = el('figure', { class: 'plot', 'data-plot': spec.key });
      const caption = el('figcaption', {}, spec.title);
      figure.append(caption);
      this.container.append(figure);
      const series = [{ label: 'time' }];
      const fmt = (u, v) => (v === null || v === undefined ? '–' : v.toFixed(spec.digits));
      if (spec.lines) {
        for (const [, label, stroke] of spec.lines) series.push({ label, stroke, width: 2, spanGaps: true, value: fmt });
      } else {
        if (spec.measured) series.push({ label: 'measured', stroke: COLOURS.measured, width: 1, spanGaps: true, value: fmt });
        series.push({ label: 'estimated', stroke: COLOURS.estimated, width: 2, spanGaps: true, value: fmt });
        series.push({ label: 'true', stroke: COLOURS.truth, width: 1.5, dash: [6, 4], spanGaps: true, value: fmt });
      }
      if (spec.warn) {
        for (const [name, colour] of [
          ['WARN', COLOURS.warn],
          ['FAULT', COLOURS.fault],
        ]) {
          const line = { label: name, stroke: colour, width: 1, dash: [3, 3], points: { show: false }, value: fmt };
          series.push(line);
          if (!spec.oneSided) series.push({ ...line, label: `−${name}`, class: 'mirror' }); // the negative side, not in the legend
        }
      }
      const options = {
        width,
        height: PLOT_HEIGHT,
        series,
        legend: { live: true },
        cursor: { drag: { x: false, y: false } },
        scales: { x: { time: true, range: (u, min, max) => this.xRange(min, max) } },
        axes: [{}, { size: 60 }],
        hooks: {
          draw: [(u) => this.markAlarm(u)],
          setScale: [
            (u, key) => {
              if (key !== 'x') return;
              figure.dataset.xMin = String(u.scales.x.min);
              figure.dataset.xMax = String(u.scales.x.max);
            },
          ],
        },
      };
      const chart = new uPlot(options, series.map(() => []), figure);
      figure.setAttribute('role', 'group');
      figure.setAttribute('aria-label', spec.title);
      this.plots.push({ spec, chart, figure });
    }
    this.fit();
  }

  /** Live: the last history_s seconds, or from the first sample while there is less; a look-back: its span. */
  xRange(min, max) {
    if (this.lookback) return [this.lookback.startS, this.lookback.endS];
    return [Math.max(min, max - this.historyS), max];
  }

  /** A look-back marks the alarm's time with a vertical line. */
  markAlarm(u) {
    if (!this.lookback) return;
    const x = u.valToPos(this.lookback.atS, 'x', true);
    const { ctx, bbox } = u;
    ctx.save();
    ctx.strokeStyle = COLOURS.fault;
    ctx.lineWidth = 2 * devicePixelRatio;
    ctx.setLineDash([4 * devicePixelRatio, 4 * devicePixelRatio]);
    ctx.beginPath();
    ctx.moveTo(x, bbox.top);
    ctx.lineTo(x, bbox.top + bbox.height);
    ctx.stroke();
    ctx.restore();
  }

  fit() {
    if (!this.plots.length) return;
    for (const plot of this.plots) {
      const width = Math.max(300, plot.figure.clientWidth - 16);
      if (Math.abs(plot.chart.width - width) > 2) plot.chart.setSize({ width, height: PLOT_HEIGHT });
    }
  }

  onHello(hello) {
    this.historyS = hello.history_s;
    this.pointNames = hello.point_columns;
    this.pointColumns = Object.fromEntries(hello.point_columns.map((name, i) => [name, i]));
    this.truthColumns = Object.fromEntries(hello.truth_columns.map((name, i) => [name, i]));
  }

  onStatus(status) {
    this.status = status;
    const [, profile, level, seen] = status.row;
    this.level.textContent = level;
    this.level.className = `level level-${level}`;
    const nowS = status.now_s;
    const t = status.thresholds;
    const facts = [
      ['profile', 'Profile', profile],
      ['gains', 'Gains', shortHash(status.gain_version)],
      ['seen', 'Last seen', seen === null ? 'never' : age(nowS - seen)],
      ['seq', 'Last sample', status.last_seq === null ? '–' : `#${status.last_seq}`],
      ['payload', 'Payload', status.payload_kg > 0 ? `${status.payload_kg} kg` : 'none reported'],
      ['grade', 'Road grade', roadGrade(status)],
      ['judged', 'Fault alarms', judging(status)],
      ['truth', 'Ground truth', status.truth ? 'shown' : 'none published'],
      ['torque', 'Torque thresholds', `WARN ${t.torque_warn_nm} / FAULT ${t.torque_fault_nm} N m`],
      ['steer', 'Steering thresholds', `WARN ${t.steer_warn_rad} / FAULT ${t.steer_fault_rad} rad`],
    ];
    if (status.effectiveness) {
      facts.push(['effectiveness', 'Effectiveness thresholds', `WARN below ${t.effectiveness_warn} / FAULT below ${t.effectiveness_fault}`]);
    }
    this.facts.replaceChildren(
      ...facts.map(([key, name, value]) => el('div', { 'data-fact': key }, el('dt', {}, name), el('dd', {}, value))),
    );
    this.facts.dataset.level = level;
  }

  /** What the vehicle carries, as an operator reports it (PUT /vehicles/{id}/payload; needs the API token). */
  async reportPayload() {
    const vehicle = this.vehicle;
    const payloadKg = Number(this.payloadInput.value);
    const button = this.payloadForm.querySelector('button');
    button.disabled = true;
    this.showPayloadStatus('', 'Reporting…');
    try {
      const answer = await api('PUT', `/vehicles/${encodeURIComponent(vehicle)}/payload`, { payload_kg: payloadKg });
      if (vehicle === this.vehicle) this.showPayloadStatus('done', `Reported: ${answer.payload_kg} kg`);
    } catch (err) {
      const problems = err.problems && err.problems.length ? ` (${err.problems.join('; ')})` : '';
      if (vehicle === this.vehicle) this.showPayloadStatus('error', `Not reported: ${err.message}${problems}`);
      if (err.status === 401) this.onUnauthorized();
    } finally {
      button.disabled = false;
    }
  }

  showPayloadStatus(state, text) {
    this.payloadStatus.dataset.state = state;
    this.payloadStatus.textContent = text;
  }

  /** A "trace" frame: the history on connect (or after a reset), then the new points. */
  onTrace(frame) {
    if (frame.history) {
      this.points = frame.points;
      this.truth = frame.truth;
    } else {
      this.points.push(...frame.points);
      this.truth.push(...frame.truth);
    }
    this.trim();
    if (!this.lookback) this.scheduleDraw();
  }

  /** Show the estimates of history_s centred on ``alarm``'s time from the estimate history, until backToLive. */
  async lookBack(alarm) {
    if (!this.pointNames) return;
    const request = ++this.lookbackRequest;
    const vehicle = this.vehicle;
    const half = this.historyS / 2;
    const atS = alarm.raised_t_ns / 1e9;
    const start = (atS - half).toFixed(3);
    const end = (atS + half).toFixed(3);
    const what = `the ${(ALARM_KINDS[alarm.kind] || alarm.kind).toLowerCase()} raised at ${clock(alarm.raised_t_ns)}`;
    this.showBanner('loading', `Loading the estimates around ${what}…`);
    let answer;
    try {
      const query = new URLSearchParams({ start, end });
      answer = await api('GET', `/vehicles/${encodeURIComponent(vehicle)}/estimates?${query}`);
    } catch (err) {
      if (request !== this.lookbackRequest || vehicle !== this.vehicle) return;
      this.lookback = null;
      this.container.dataset.mode = 'live';
      this.draw();
      this.showBanner('failed', `Could not load the estimates around ${what}: ${err.message}. The plots show live data.`);
      if (err.status === 401) this.onUnauthorized();
      return;
    }
    if (request !== this.lookbackRequest || vehicle !== this.vehicle) return; // superseded, or the view left
    // a plot point per estimate; the history keeps no measurement and no ground truth: those columns stay empty
    const names = this.pointNames;
    const points = answer.estimates.map((row) => names.map((name) => (name === 't' ? row.t_ns / 1e9 : (row[name] ?? null))));
    // what is shown instead of the live plots until backToLive
    this.lookback = { alarm, atS, startS: Number(start), endS: Number(end), points };
    Object.assign(this.lookbackBox.dataset, { start, end, alarmT: String(atS), count: String(points.length) });
    const span = `${clock(Number(start) * 1e9)} to ${clock(Number(end) * 1e9)}`;
    this.showBanner(
      'shown',
      `Looking back: ${points.length} estimates from ${span} around ${what} (dashed red line), from the estimate history (estimates only: it keeps no measurement and no ground truth).`,
    );
    this.container.dataset.mode = 'history';
    this.draw();
  }

  backToLive() {
    this.showLive();
    this.draw();
  }

  showLive() {
    this.lookbackRequest += 1;
    this.lookback = null;
    this.lookbackBox.hidden = true;
    this.lookbackBox.dataset.state = 'live';
    this.container.dataset.mode = 'live';
  }

  showBanner(state, text) {
    this.lookbackBox.dataset.state = state;
    this.lookbackText.textContent = text;
    this.lookbackBox.hidden = false;
  }

  trim() {
    const last = Math.max(this.points.at(-1)?.[0] ?? -Infinity, this.truth.at(-1)?.[0] ?? -Infinity);
    const oldest = last - this.historyS;
    const drop = (rows) => {
      let n = 0;
      while (n < rows.length && rows[n][0] < oldest) n += 1;
      if (n) rows.splice(0, n);
    };
    drop(this.points);
    drop(this.truth);
  }

  scheduleDraw() {
    if (this.timer) return;
    const wait = Math.max(0, MIN_REDRAW_MS - (performance.now() - this.lastDraw));
    this.timer = setTimeout(() => {
      this.timer = 0;
      requestAnimationFrame(() => this.draw());
    }, wait);
  }

  draw() {
    if (!this.plots.length || !this.pointColumns) return;
    const started = performance.now();
    this.lastDraw = started;
    const P = this.pointColumns;
    const T = this.truthColumns;
    const points = this.lookback ? this.lookback.points : this.points;
    const truth = this.lookback ? [] : this.truth;
    const { x, ia, ib } = mergeByTime(points, truth);
    const fromPoints = (name) => ia.map((i) => (i < 0 ? null : points[i][P[name]]));
    const fromTruth = (name) => ib.map((j) => (j < 0 ? null : truth[j][T[name]]));
    const thresholds = this.status ? this.status.thresholds : null;
    for (const { spec, chart, figure } of this.plots) {
      figure.hidden = Boolean(spec.optional) && !(this.status && this.status[spec.optional]);
      const data = [x];
      if (spec.lines) {
        for (const [name] of spec.lines) data.push(fromPoints(name));
      } else {
        if (spec.measured) data.push(fromPoints(spec.measured));
        data.push(fromPoints(spec.estimated));
        data.push(fromTruth(spec.truth));
      }
      if (spec.warn) {
        const warn = thresholds ? thresholds[spec.warn] : null;
        const fault = thresholds ? thresholds[spec.fault] : null;
        const levels = spec.oneSided ? [warn, fault] : [warn, warn === null ? null : -warn, fault, fault === null ? null : -fault];
        for (const value of levels) data.push(x.map(() => value));
      }
      chart.setData(data);
      figure.dataset.points = String(x.length);
      figure.dataset.estimates = String(points.length);
      figure.dataset.truth = String(truth.length);
      figure.dataset.firstT = x.length ? String(x[0]) : '';
      figure.dataset.lastT = x.length ? String(x[x.length - 1]) : '';
      const latest = points.at(-1);
      figure.dataset.latest = latest ? fixed(latest[P[spec.lines ? spec.lines[0][0] : spec.estimated]], spec.digits) : '';
    }
    performance.measure('vehicle-draw', { start: started, end: performance.now() });
  }
}
