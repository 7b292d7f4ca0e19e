"""``magcal`` with real sensor streams: ``simulate`` writes them, ``correct`` applies the calibration's time
offsets, ``--sync-mode``/``--max-gap`` choose the rule (subprocesses, as a user runs them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_input_defects import simulate_refused
from test_offline import magcal, ok

from magcal_ros.core.metrics import tensor_floor
from magcal_ros.core.units import NT
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.csv_recording import TENSOR_COLUMNS
from magcal_ros.io.truth_file import load_truth

FLOOR = tensor_floor(1 * NT, 0.4)
TURN = ("--schedule", "single-axis", "--axis", "y", "--count", "2000", "--rate", "100")
"""Ten seconds of a turn at 2 pi 100 / 2000 = 0.31 rad/s (16,000 nT/s) about y."""


def tensor_rms(csv: Path) -> tuple[int, float]:
    """Sets and tensor RMS against the floor of a corrected CSV."""
    data = np.genfromtxt(csv, delimiter=",", names=True)
    g = np.stack([data[c.replace(".", "")] for c in TENSOR_COLUMNS], axis=1)
    return len(data), float(np.sqrt(np.mean(g**2)) / FLOOR)


def test_a_lag_is_simulated_and_corrected_with_its_time_offset(tmp_path: Path) -> None:
    """mag3 reads 5 ms late on sensors sampled 2.5 ms apart and stamped on receipt: the truth YAML
    carries it as mag3.time_offset, and 'magcal correct' with it keeps the tensor at the floor;
    without it (the same calibration, offset removed) the tensor is many times the floor."""
    bag = tmp_path / "streams"
    out = ok(magcal("simulate", bag, *TURN, "--phases", "0,0.0025,0.005,0.0075", "--receipt-jitter", "0.0002",
                    "--lags", "0,0,0.005,0", "--glitch", "mag2,4,2", "--restart", "6,60,mag4")).stdout
    assert "mag3 5 ms" in out
    truth = calfile.read(f"{bag}.truth.yaml")
    assert truth.time_offsets.tolist() == [0.0, 0.0, 0.005, 0.0]
    arrays = load_truth(bag)
    assert len(arrays["stamps_mag4"]) == len(arrays["instants_mag4"]) and arrays["stamps_mag4"][-1] < arrays["instants_mag4"][-1]
    csv = tmp_path / "corrected.csv"
    proc = ok(magcal("correct", bag, "-c", f"{bag}.truth.yaml", "-o", csv))
    assert "1 messages with a stamp far off" in proc.stderr and "1 source restarts" in proc.stderr
    sets, rms = tensor_rms(csv)
    assert sets >= 0.98 * len(arrays["stamps_mag1"]) and rms < 1.3
    no_lag = tmp_path / "no_lag.yaml"
    no_lag.write_text(Path(f"{bag}.truth.yaml").read_text().replace("time_offset: 0.005", "time_offset: 0.0"))
    ok(magcal("correct", bag, "-c", no_lag, "-o", tmp_path / "wrong.csv"))
    assert tensor_rms(tmp_path / "wrong.csv")[1] > 3


def test_sync_mode_and_max_gap_options(tmp_path: Path) -> None:
    """Sensors sampled apart: auto interpolates (every set kept); forced exact keeps none and says so;
    time offsets with --sync-mode exact are refused; a bad --max-gap is a usage error."""
    bag = tmp_path / "phased"
    ok(magcal("simulate", bag, *TURN, "--phases", "0,0.0025,0.005,0.0075", "--lags", "0,0,0.001,0"))
    csv = tmp_path / "c.csv"
    ok(magcal("correct", bag, "-c", f"{bag}.truth.yaml", "-o", csv, "--max-gap", "0.05"))
    assert tensor_rms(csv)[1] < 1.3
    refused = magcal("correct", bag, "-c", f"{bag}.truth.yaml", "-o", tmp_path / "x.csv", "--sync-mode", "exact")
    assert refused.returncode == 2 and "mag3 1 ms" in refused.stderr and "interpolate" in refused.stderr
    exact = magcal("calibrate", bag, "-o", tmp_path / "cal.yaml", "--sync-mode", "exact")
    assert exact.returncode == 2 and "no complete synchronized sets" in exact.stderr
    bad = magcal("correct", bag, "-c", f"{bag}.truth.yaml", "-o", tmp_path / "y.csv", "--max-gap", "-1")
    assert bad.returncode == 2 and "max_gap" in bad.stderr


def test_csv_columns_are_shifted_by_their_time_offsets(tmp_path: Path) -> None:
    """A CSV recording (one stamp per row) corrected with a calibration that has a time offset: that
    sensor's column is shifted and interpolated to the first sensor's instants."""
    raw = tmp_path / "r.csv"
    ok(magcal("simulate", raw, *TURN))
    cal = calfile.read(f"{raw}.truth.yaml")
    lagging = calfile.dumps(cal).replace("    mag2:\n", "    mag2:\n      time_offset: 0.02\n")
    (tmp_path / "lag.yaml").write_text(lagging)
    plain, shifted = tmp_path / "plain.csv", tmp_path / "shifted.csv"
    ok(magcal("correct", raw, "-c", f"{raw}.truth.yaml", "-o", plain))
    ok(magcal("correct", raw, "-c", tmp_path / "lag.yaml", "-o", shifted))
    a = np.genfromtxt(plain, delimiter=",", names=True)
    b = np.genfromtxt(shifted, delimiter=",", names=True)
    # mag2's reading at a row's instant is the field 20 ms (two rows) later: its column moved two rows.
    at = {t: i for i, t in enumerate(a["stamp"])}
    rows = [(at[t], i) for i, t in enumerate(b["stamp"]) if t in at and at[t] + 2 < len(a)]
    assert len(rows) > 1900
    ia, ib = np.array(rows).T
    assert np.allclose(b["mag2x"][ib], a["mag2x"][ia + 2], atol=1e-12)
    assert np.array_equal(b["mag1x"][ib], a["mag1x"][ia])


@pytest.mark.parametrize("option", ["--phases", "--lags"])
def test_stream_options_need_a_bag(tmp_path: Path, option: str) -> None:
    proc = magcal("simulate", tmp_path / "s.csv", option, "0,0,0.001,0")
    assert proc.returncode == 2 and "rosbag2" in proc.stderr


STREAM_REFUSALS: list[tuple[tuple[object, ...], str]] = [
    # a sensor left without messages: which and why
    (("--phases", "100,0,0,0"), "mag1 has no messages: its first sample (--phases 100 s) is after the 19.9 s of the streams"),
    (("--sensor-rate", 0.001), ("mag1 has no messages: it samples every 1000 s (--sensor-rate 0.001 Hz, --clock-ppm 0), "
                                "longer than the 19.9 s it records")),
    (("--lags", "0,30,0,0"), "mag2 has no messages: its readings lag their instants by 30 s (--lags)"),
    (("--lags", "-30,0,0,0"), "the streams last -10.1 s (the attitudes' span less the largest lead of --lags)"),
    (("--loss", 0.9999), "mag1 has no messages: --loss 0.9999 lost all 198 of them"),
    # values beyond a physical or sane range
    (("--phases", 1e9), "--phases must be finite seconds within +-1e+06, got 1e+09"),
    (("--receipt-delay", 1e9), "--receipt-delay must be finite seconds within +-1e+06, got 1e+09"),
    (("--receipt-jitter=-1",), "--receipt-jitter must be a standard deviation of 0 .. 1e+06 s"),
    (("--loss", 1), "--loss must be a fraction in [0, 1), got 1"),
    (("--clock-ppm", 1e9), "--clock-ppm must be within +-100000 ppm (a clock off by more is not a clock error), got 1e+09"),
    (("--clock-ppm", "0,-1e6,0,0"), ("--clock-ppm must be within +-100000 ppm (a clock off by more is not a clock error), "
                                     "got 0,-1e+06,0,0")),
    (("--sensor-rate", 1e9), ("mag1 would sample 1.99e+10 times (--sensor-rate 1e+09 Hz from --phases 0 s over 19.9 s): "
                              "more messages than magcal simulates, at most 10000000")),
    (("--sensor-rate", 2e9), "--sensor-rate must be positive, at most 1e+09 Hz (a sample period of at least 1 ns)"),
    (("--glitch", "mag1,1,-1e12"), "--glitch TIME,SHIFT must be finite seconds within +-1e+06, got 1,-1e+12"),
    (("--restart", "1,-1e12"), "--restart TIME,JUMP must be finite seconds within +-1e+06, got 1,-1e+12"),
    # stamps a ROS stamp (int32 sec) cannot hold
    (("--start-time", 2147483000, "--receipt-delay", 1000),
     ("--start-time 2147483000 s with --receipt-delay 1000 s and --receipt-jitter 0 s puts a stamp of mag1 at 2147484020 s: "
      "a ROS stamp holds 0 .. 2147483647 s")),
    (("--start-time", 10, "--receipt-delay=-10"), ("--start-time 10 s with --receipt-delay -10 s and --receipt-jitter 0 s "
                                                   "puts a stamp of mag1 at 0 s")),
    (("--start-time", 1e5, "--restart", "1,9e5"), "--restart 1,900000 puts a stamp of mag1 at -799999 s"),
    (("--start-time", 1e5, "--glitch", "mag2,1,-9e5"), "--glitch mag2,1,-900000 puts a stamp of mag2 at -799999 s"),
]
"""Stream options ``magcal simulate`` refuses (with ``--count 200``: 19.9 s at 10 Hz) and the start of the line."""


@pytest.mark.parametrize(("args", "says"), STREAM_REFUSALS, ids=[" ".join(map(str, a)) for a, _ in STREAM_REFUSALS])
def test_stream_options_that_cannot_be_simulated_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                               args: tuple[object, ...], says: str) -> None:
    """Tracebacks before (an empty stream's CDR, an infinite or huge int, a 148 GiB array) or exit 0 with
    wrapped stamps: now exit 2, one line naming the option, nothing written."""
    simulate_refused(tmp_path, capsys, ("--count", 200, *args), says)
