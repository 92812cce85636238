// Bucket ownership changes of the fleet's service replicas (bucket leases): which replica took or handed over
// which of the 16 vehicle buckets, newest first. Fed by the fleet stream's "ownership" frames (every replica's
// announcements, whichever replica the page is connected to); hidden while there is none.

import { clock, el } from './format.js';

const MAX_SHOWN = 20;

const plural = (n, word) => `${n} ${word}${n === 1 ? '' : 's'}`;
const bucketIndex = (bucket) => parseInt(bucket.slice(1), 16);

/** Buckets in words: b00, b01, b02, b05 as "b00–b02, b05" (three or more in a row as a range). */
function bucketRanges(buckets) {
  const sorted = [...buckets].sort();
  const parts = [];
  for (let i = 0; i < sorted.length; ) {
    let j = i;
    while (j + 1 < sorted.length && bucketIndex(sorted[j + 1]) === bucketIndex(sorted[j]) + 1) j += 1;
    if (j - i >= 2) parts.push(`${sorted[i]}–${sorted[j]}`);
    else parts.push(...sorted.slice(i, j + 1));
    i = j + 1;
  }
  return parts.join(', ');
}

export class OwnershipList {
  /**
   * @param {HTMLElement} box  shown once there is a change
   * @param {HTMLOListElement} list
   */
  constructor(box, list) {
    this.box = box;
    this.list = list;
    this.changes = [];
    this.replica = '';
  }

  /** A frame {full, changes: [OwnershipChange]} (oldest first) from a stream of ``replica``. */
  apply(frame, replica) {
    this.replica = replica;
    if (frame.full) this.changes = [];
    this.changes = [...this.changes, ...frame.changes].slice(-MAX_SHOWN);
    this.render();
  }

  clear() {
    this.changes = [];
    this.render();
  }

  render() {
    this.list.replaceChildren(...this.changes.map((change) => this.item(change)).reverse());
    this.box.hidden = this.changes.length === 0;
  }

  item(change) {
    const who = change.replica === this.replica ? `${change.replica} (this replica)` : change.replica;
    const what = [];
    if (change.gained.length) what.push(`took ${bucketRanges(change.gained)}`);
    if (change.lost.length) what.push(`handed over ${bucketRanges(change.lost)}`);
    const moved = change.gained.length + change.lost.length;
    const serves = change.buckets.length ? plural(change.buckets.length, 'bucket') : 'no bucket';
    return el(
      'li',
      {
        class: 'ownership',
        'data-replica': change.replica,
        'data-change': change.gained.length ? (change.lost.length ? 'both' : 'gained') : 'lost',
        'data-buckets': [...change.gained, ...change.lost].join(' '),
      },
      el('span', { class: 'ownership-what' }, `Replica ${who} ${what.join(' and ')}`),
      el(
        'span',
        { class: 'ownership-meta' },
        `${clock(change.t_ns)} · ${plural(moved, 'bucket')}, ${plural(change.vehicles, 'vehicle')} · it serves ${serves} now`,
      ),
    );
  }
}
