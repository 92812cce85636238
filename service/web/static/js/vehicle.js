// The vehicle view: live uPlot time plots of the last history_s seconds, like the paper's Figs. 4 and 6:
// measured and estimated v_x and r, estimated v_y, the fault estimates with their alarm thresholds, and the
// simulator's ground truth when it publishes one.

import { AlarmList } from './alarms.js';
import { age, el, fixed, levelBadge, shortHash } from './format.js';

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

export class VehicleView {
  constructor(alarms, onUnauthorized) {
    this.alarmsStore = alarms;
    this.onUnauthorized = onUnauthorized;
    this.title = document.getElementById('vehicle-title');
    this.level = document.getElementById('vehicle-level');
    this.facts = document.getElementById('vehicle-facts');
    this.missing = document.getElementById('vehicle-missing');
    this.container = document.getElementById('plots');
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
    this.truthColumns = null;
    this.lastDraw = 0;
    this.timer = 0;
    this.title.textContent = vehicle;
    this.level.replaceWith((this.level = levelBadge('–')));
    this.level.id = 'vehicle-level';
    this.facts.replaceChildren();
    this.missing.hidden = true;
    this.alarmList = new AlarmList(document.getElementById('vehicle-alarms'), this.alarmsStore, {
      vehicle,
      box: document.getElementById('vehicle-alarms-box'),
      onUnauthorized: this.onUnauthorized,
    });
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
        scales: {
          x: {
            time: true,
            // the last history_s seconds, or from the first sample while there is less
            range: (u, min, max) => [Math.max(min, max - this.historyS), max],
          },
        },
        axes: [{}, { size: 60 }],
      };
      const chart = new uPlot(options, series.map(() => []), figure);
      figure.setAttribute('role', 'group');
      figure.setAttribute('aria-label', spec.title);
      this.plots.push({ spec, chart, figure });
    }
    this.fit();
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
    this.scheduleDraw();
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
    const { x, ia, ib } = mergeByTime(this.points, this.truth);
    const fromPoints = (name) => ia.map((i) => (i < 0 ? null : this.points[i][P[name]]));
    const fromTruth = (name) => ib.map((j) => (j < 0 ? null : this.truth[j][T[name]]));
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
      figure.dataset.estimates = String(this.points.length);
      figure.dataset.truth = String(this.truth.length);
      figure.dataset.lastT = x.length ? String(x[x.length - 1]) : '';
      const latest = this.points.at(-1);
      figure.dataset.latest = latest ? fixed(latest[P[spec.lines ? spec.lines[0][0] : spec.estimated]], spec.digits) : '';
    }
    performance.measure('vehicle-draw', { start: started, end: performance.now() });
  }
}
