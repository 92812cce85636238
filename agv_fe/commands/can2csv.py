"""`agv-fe can2csv`: a recording (the replay/calibrate CSV) from a CAN log and its DBC file."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, fail


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "can2csv",
        help="turn a CAN log and its DBC into a recording for replay and calibrate",
        description="Decode a CAN log (candump .log, .asc, .blf, .trc, ... by extension) with its DBC file, take the "
        "four signals a mapping file names (message, signal, scale and offset to the protocol's units: "
        "docs/usage.md; and the road's grade when it names one), and write them on the 10 ms grid (the latest "
        "value at each grid point) as the recording CSV that `agv-fe replay` and `agv-fe calibrate` read. Needs "
        "the 'can' extra (cantools, python-can).",
    )
    parser.add_argument("log", metavar="LOG", help="CAN log")
    parser.add_argument("--dbc", required=True, metavar="FILE.dbc", help="the vehicle's CAN database")
    parser.add_argument("--map", required=True, metavar="MAP.yaml", help="which signal is which column")
    parser.add_argument("--out", required=True, metavar="REC.csv", help="the recording to write")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from edge_client.recording import RecordingError, write_recording

    try:
        try:
            from edge_client.can_log import load_mapping, read_can_log
        except ImportError as exc:  # cantools or python-can missing
            raise CommandError(
                f"can2csv needs cantools and python-can: pip install 'agv-fault-estimator[can]' ({exc})"
            ) from exc
        try:
            mapping = load_mapping(args.map)
            recording, stats = read_can_log(args.log, args.dbc, mapping)
        except RecordingError as exc:
            raise CommandError(str(exc)) from exc
    except CommandError as exc:
        return fail(exc)
    out = Path(args.out)
    try:
        grade = None if recording.grade is None else {"grade": recording.grade}
        write_recording(out, recording.t, recording.y, recording.u, extra=grade)
    except OSError as exc:
        return fail(CommandError(f"{out}: cannot write: {exc.strerror}"))
    used = ", ".join(f"{column} {count}" for column, count in stats.used.items())
    print(
        f"read {stats.frames} frames: used {used}; {stats.other} of other messages, {stats.undecodable} undecodable; "
        f"every column known from t = {stats.first_complete_s:.3f} s of the log"
    )
    print(f"written {out}: {len(recording)} samples ({recording.t[-1]:.2f} s at {mapping.sample_period_s * 1000:g} ms)")
    return 0
