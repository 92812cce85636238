import pytest

from edge_client.recording import RecordingError, parse_recording

HEADER = "t,vx,r,torque,steer,comment\n"


def rows(*lines: str) -> list[str]:
    return [HEADER, *[line + "\n" for line in lines]]


def test_valid_recording_ignores_extra_columns():
    rec = parse_recording(rows("0.00,10,0.1,100,0.01,a", "0.01,10.1,0.1,100,0.01,b", "0.02,10.2,0.1,100,0.01,c"))
    assert len(rec) == 3 and rec.y[2, 0] == 10.2 and rec.u[0, 1] == 0.01


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        (("0.00,10,0.1,100,0.01,a", "0.01,nan,0.1,100,0.01,b"), "line 3: column 'vx' is not finite"),
        (("0.00,10,0.1,100,0.01,a", "0.01,10,abc,100,0.01,b"), "line 3: column 'r' is not a number"),
        (("0.00,10,0.1,100,0.01,a", "0.01,10,0.1,100,0.01,b", "0.05,10,0.1,100,0.01,c"), "line 4: time step 0.04 s"),
        (("0.00,10,0.1,100,0.01,a", "0.01,10"), "line 3: expected 6 fields"),
        (("0.00,10,0.1,100,0.01,a",), "at least 2 data rows"),
    ],
)
def test_bad_rows_are_named(lines, message):
    with pytest.raises(RecordingError, match=message):
        parse_recording(rows(*lines))


def test_missing_columns_are_listed():
    with pytest.raises(RecordingError, match="missing column\\(s\\) torque, steer"):
        parse_recording(["t,vx,r\n", "0,1,2\n", "0.01,1,2\n"])
