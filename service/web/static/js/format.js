// Small DOM and formatting helpers shared by the views.

/** Create an element: el('a', {href: '#/', class: 'x'}, 'text', child, ...). */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === 'class') node.className = value;
    else if (key === 'text') node.textContent = value;
    else if (key.startsWith('on')) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? '' : String(value));
  }
  for (const child of children) {
    if (child === undefined || child === null || child === false) continue;
    node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

export const LEVEL_RANK = { FAULT: 3, WARN: 2, STALE: 1, OK: 0 };
export const LEVELS = ['FAULT', 'WARN', 'STALE', 'OK'];

export const ALARM_KINDS = {
  torque_fault: 'Torque fault',
  steer_fault: 'Steering fault',
  torque_effectiveness: 'Drive-torque effectiveness lost',
  steer_effectiveness: 'Steering effectiveness lost',
  out_of_domain: 'Outside the design domain',
  stale: 'No data (stale)',
  unserved: 'No replica serves it (unserved)',
  rejected_inputs: 'Rejected measurements',
  sequence_rejected: 'Samples refused as late',
};

export function levelBadge(level) {
  return el('span', { class: `level level-${level}` }, level);
}

export function fixed(value, digits) {
  return value === null || value === undefined || Number.isNaN(value) ? '–' : Number(value).toFixed(digits);
}

/** "just now", "12 s ago", "3 min ago", "2 h ago" for an age in seconds. */
export function age(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return 'never';
  if (seconds < 1.5) return 'just now';
  if (seconds < 90) return `${Math.round(seconds)} s ago`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min ago`;
  return `${Math.round(seconds / 3600)} h ago`;
}

export function clock(ns) {
  if (!ns) return '–';
  return new Date(ns / 1e6).toLocaleTimeString([], { hour12: false });
}

export function shortHash(hash) {
  return hash ? String(hash).slice(0, 12) : '–';
}
