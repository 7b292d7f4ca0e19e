"""``magcal batch``: a campaign on Dask, outputs identical to ``magcal correct``, failures by name,
re-runs that skip finished work, and the report checked in a real browser.

A real Dask scheduler and two workers run as separate processes on localhost (ports chosen
by the operating system, found through the scheduler file); the batch runs as a user runs
it, ``python -m magcal_ros.app.cli batch ...`` in a subprocess. Recordings are small (300
sets) so the tests stay light on CPU.
"""

from __future__ import annotations

import csv
import html.parser
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader

from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import format_seconds, parse_seconds
from magcal_ros.core.units import NT
from magcal_ros.io import cdr
from magcal_ros.io.bag_writer import write_recording_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.sim.spec import SimulationSpec, run

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("mag1", "mag2", "mag3", "mag4")
F = 5.5e-5  # the simulator's default intensity (T)
NOISE = 1.0 * NT
SEED = 5
SETS = 300
T0 = 1_700_000_000.0
DAY = 86_400.0
DRIFT = 20 * NT
"""A hard-iron change between two missions of auv1: every sensor's raw x reads DRIFT more."""
GOOD = ("auv1/m1_bag", "auv1/m2_bag", "auv2/m1.csv")
CORRUPT = "auv2/corrupt_bag"
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync")


def magcal(*args: object, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """``python -m magcal_ros.app.cli ARGS`` in a subprocess."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=timeout)


def ok(proc: subprocess.CompletedProcess[str]) -> subprocess.CompletedProcess[str]:
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def recording(start: float, count: int = SETS) -> Recording:
    """Raw sets of the simulated array (same sensors for every ``SEED``), stamps from ``start``."""
    rec, _, _ = run(SimulationSpec(count=count, seed=SEED, start_time=start, noise=NOISE))
    return rec


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """campaign/auv1/{m1_bag (sqlite3), m2_bag (mcap, hard iron drifted)}, campaign/auv2/{m1.csv (one
    repeated row), corrupt_bag (storage cut in half)} and the calibration from a separate manoeuvre."""
    d = tmp_path_factory.mktemp("batch")
    rotation = d / "rotation.csv"
    write_csv(rotation, recording(T0 - DAY, 500))
    cal = d / "cal.yaml"
    ok(magcal("calibrate", rotation, "-o", cal, "--reference-field", F))
    camp = d / "campaign"
    (camp / "auv1").mkdir(parents=True)
    (camp / "auv2").mkdir()
    write_recording_bag(camp / "auv1" / "m1_bag", recording(T0), "sqlite3")
    drifted = recording(T0 + 2 * DAY)
    drifted.vectors[:, :, 0] += DRIFT
    write_recording_bag(camp / "auv1" / "m2_bag", drifted, "mcap")
    write_csv(camp / "auv2" / "m1.csv", recording(T0 + DAY))
    lines = (camp / "auv2" / "m1.csv").read_text().splitlines(keepends=True)
    (camp / "auv2" / "m1.csv").write_text("".join(lines[:50] + [lines[49]] + lines[50:]))  # a repeated stamp
    write_recording_bag(camp / "auv2" / "corrupt_bag", recording(T0 + 3 * DAY), "sqlite3")
    storage = next((camp / "auv2" / "corrupt_bag").glob("*.db3"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    return {"dir": d, "campaign": camp, "cal": cal, "rotation": rotation}


class DaskCluster:
    """A scheduler and two single-threaded workers, each its own process, on localhost."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.procs: list[subprocess.Popen[bytes]] = []
        self.log = open(folder / "dask.log", "wb")
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
        scheduler_file = folder / "scheduler.json"
        self._start([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                     "--no-dashboard", "--scheduler-file", str(scheduler_file)], env)
        deadline = time.monotonic() + 120
        while not scheduler_file.exists():
            assert time.monotonic() < deadline, "the Dask scheduler did not start: " + self.logs()
            assert self.procs[0].poll() is None, "the Dask scheduler exited: " + self.logs()
            time.sleep(0.2)
        self.address = json.loads(scheduler_file.read_text())["address"]
        for i in range(2):
            self._start([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(scheduler_file),
                         "--nthreads", "1", "--no-nanny", "--no-dashboard", "--host", "127.0.0.1", "--name", f"w{i}",
                         "--local-directory", str(folder / f"w{i}")], env)
        from distributed import Client

        with Client(self.address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            self.worker_pids = set(client.run(os.getpid).values())
            self.worker_addresses = sorted(client.scheduler_info()["workers"])

    def _start(self, argv: list[str], env: dict[str, str]) -> None:
        self.procs.append(subprocess.Popen(argv, stdout=self.log, stderr=self.log, env=env, cwd=self.folder))

    def logs(self) -> str:
        self.log.flush()
        return (self.folder / "dask.log").read_text(errors="replace")[-3000:]

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.terminate()
        for p in reversed(self.procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.log.close()


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Any:
    cluster = DaskCluster(tmp_path_factory.mktemp("dask"))
    try:
        yield cluster
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def cluster_run(campaign: dict[str, Path], dask_cluster: DaskCluster) -> dict[str, Any]:
    """The campaign corrected through --scheduler on the cluster above."""
    out = campaign["dir"] / "out"
    proc = magcal("batch", campaign["campaign"], "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address)
    return {"out": out, "proc": proc}


def messages(bag: Path) -> list[tuple[str, str, int, bytes]]:
    """Every message of a bag, in order: topic, type, bag time, serialized bytes."""
    with Reader(bag) as reader:
        return [(c.topic, c.msgtype, t, bytes(d)) for c, t, d in reader.messages()]


def storage_of(bag: Path) -> str:
    return "mcap" if any(bag.glob("*.mcap")) else "sqlite3"


def test_a_campaign_on_a_dask_cluster_is_magcal_correct_per_recording(
        campaign: dict[str, Path], dask_cluster: DaskCluster, cluster_run: dict[str, Any], tmp_path: Path) -> None:
    proc, out = cluster_run["proc"], cluster_run["out"]
    assert proc.returncode == 1, "a failed recording makes the exit code non-zero: " + proc.stdout + proc.stderr
    # The corrupt recording is named, with the reason 'magcal correct' gives for it alone.
    alone = magcal("correct", campaign["campaign"] / CORRUPT, "-c", campaign["cal"], "-o", tmp_path / "corrupt_out")
    assert alone.returncode == 2
    reason = alone.stderr.strip().removeprefix("magcal correct: error: ")
    assert "corrupt" in reason or "truncated" in reason, reason
    assert f"  FAILED {CORRUPT}: {reason}" in proc.stderr.splitlines(), proc.stderr
    assert "3 corrected, 0 skipped, 1 failed (auv2/corrupt_bag)" in proc.stdout
    assert not (out / CORRUPT).exists()
    assert not [p for p in (out / "auv2").iterdir() if p.name.startswith(".")], "nothing partial left"
    # The others: identical to 'magcal correct' run on each alone.
    for name in GOOD:
        target = tmp_path / "alone" / name
        ok(magcal("correct", campaign["campaign"] / name, "-c", campaign["cal"], "-o", target))
        if name.endswith(".csv"):
            assert target.read_bytes() == (out / name).read_bytes()
        else:
            assert storage_of(out / name) == storage_of(campaign["campaign"] / name)
            got, want = messages(out / name), messages(target)
            assert len(got) == 6 * SETS and got == want
    # Every task ran on the cluster's own worker processes.
    with open(out / "report.csv", newline="") as fh:
        rows = {r["recording"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {*GOOD, CORRUPT}
    pids = {int(rows[n]["worker"].rsplit(":", 1)[1]) for n in GOOD}
    assert pids <= dask_cluster.worker_pids, (pids, dask_cluster.worker_pids)
    assert rows[CORRUPT]["status"] == "failed" and rows[CORRUPT]["reason"] == reason


class DomTables(html.parser.HTMLParser):
    """The rendered page's recording rows, chart points and the root's data-ready."""

    def __init__(self) -> None:
        super().__init__()
        self.ready: str | None = None
        self.rows: dict[str, dict[str, str]] = {}
        self.points: dict[str, dict[str, float]] = {}
        self.vehicles: dict[str, dict[str, str]] = {}
        self.charts: dict[str, dict[str, str]] = {}
        self.ys: dict[str, dict[str, float]] = {}
        """Per chart, each point's y (px), and each reference line's (keys 'floor', 'flag')."""
        self.classes: dict[str, str] = {}
        self.lists: dict[str, list[str]] = {}
        self._row: dict[str, str] | None = None
        self._list = ""
        self._chart = ""

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "html":
            self.ready = a.get("data-ready")
        elif tag == "tr" and "data-name" in a:
            self._row = self.rows.setdefault(a["data-name"], {})
            self.classes[a["data-name"]] = a.get("class", "")
        elif tag == "tr" and "data-vehicle" in a:
            self._row = self.vehicles.setdefault(a["data-vehicle"], {})
        elif tag == "td" and self._row is not None and "data-key" in a:
            self._row[a["data-key"]] = a.get("data-value", "")
        elif tag == "svg":
            self._chart = a.get("data-title", "")
            self.points.setdefault(self._chart, {})
            self.charts[self._chart] = a
            self.ys.setdefault(self._chart, {})
        elif tag == "circle" and "data-recording" in a:
            self.points[self._chart][a["data-recording"]] = float(a["data-value"])
            self.ys[self._chart][a["data-recording"]] = float(a["cy"])
        elif tag == "line" and a.get("class") in ("floor", "flag"):
            self.ys[self._chart][a["class"]] = float(a["y1"])
        elif tag == "ul" and "id" in a:
            self._list = a["id"]
            self.lists[self._list] = []
        elif tag == "li" and self._list:
            self.lists[self._list].append(a.get("data-name", ""))

    def handle_endtag(self, tag: str) -> None:
        if tag == "tr":
            self._row = None
        elif tag == "ul":
            self._list = ""


def chromium_dom(page: Path) -> str:
    """The page's DOM after its script ran, from headless Chromium."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        message = "chromium is not installed (scripts/setup_env.sh installs Debian's package as root)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    with tempfile.TemporaryDirectory() as profile:
        proc = subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--dump-dom", page.as_uri()],
                              capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0 and "<html" in proc.stdout, proc.stderr[-2000:]
    return proc.stdout


def expected_from_output(path: Path, cal: Path) -> dict[str, float]:
    """The report's numbers computed here from the corrected output itself (rosbags' own decoder)."""
    if path.suffix == ".csv":
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        header, data = rows[0], np.array([r[1:] for r in rows[1:]], float)
        col = {c: i - 1 for i, c in enumerate(header)}
        stamps = [parse_seconds(r[0]) for r in rows[1:]]
        vectors = np.stack([data[:, [col[f"{n}.{a}"] for a in "xyz"]] for n in NAMES], axis=1)
        g = data[:, [col[f"gradient.{i}{j}"] for i in "xyz" for j in "xyz"]]
    else:
        ts = cdr.typestore()
        with Reader(path) as reader:
            msgs = [(c.topic, t, ts.deserialize_cdr(d, c.msgtype)) for c, t, d in reader.messages()]
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for topic, _, m in msgs if topic == "/field"]
        vectors = np.stack([np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                                      for topic, _, m in msgs if topic == f"/{n}/corrected"]) for n in NAMES], axis=1)
        g = np.array([m.data for topic, _, m in msgs if topic == "/gradient"])
    prov = yaml.safe_load(cal.read_text())["magcal_provenance"]["ros__parameters"]
    noise = float(np.sqrt(np.mean(np.square(prov["noise"]))))
    residual = np.abs(np.linalg.norm(vectors, axis=2) - F).reshape(-1)
    d = np.diff(g[:, :6], axis=0)
    return {
        "sets": len(stamps), "start": stamps[0], "end": stamps[-1], "noise": noise,
        "median": float(np.quantile(residual, 0.5, method="inverted_cdf")),
        "p95": float(np.quantile(residual, 0.95, method="inverted_cdf")),
        "tensor": float(np.sqrt(np.mean(d * d) / 2)),
    }


def test_the_report_renders_in_a_browser_with_the_outputs_numbers(
        campaign: dict[str, Path], cluster_run: dict[str, Any]) -> None:
    out = cluster_run["out"]
    page = out / "report.html"
    text = page.read_text()
    assert "src=" not in text and "href=" not in text and "@import" not in text, "self-contained: no external asset"
    dom = DomTables()
    dom.feed(chromium_dom(page))
    assert dom.ready == str(len(GOOD) + 1), "the page's script ran over every recording row"
    with open(out / "report.csv", newline="") as fh:
        rows = {r["recording"]: r for r in csv.DictReader(fh)}
    medians = dom.points["TMI residual, median"]
    for name in GOOD:
        want = expected_from_output(out / name, campaign["cal"])
        got = dom.rows[name]
        assert got["status"] == "corrected"
        assert int(got["sets"]) == want["sets"] == SETS
        assert int(got["start"]) == want["start"]
        assert float(got["duration_s"]) == pytest.approx((want["end"] - want["start"]) * 1e-9, rel=1e-12)
        assert rows[name]["start"] == format_seconds(want["start"]) and rows[name]["end"] == format_seconds(want["end"])
        assert float(got["noise_T"]) == pytest.approx(want["noise"], rel=1e-12)
        # Quantiles from the log histogram: within its 0.1 % bins.
        assert float(got["tmi_median_T"]) == pytest.approx(want["median"], rel=1.5e-3)
        assert float(got["tmi_p95_T"]) == pytest.approx(want["p95"], rel=1.5e-3)
        assert float(got["tmi_median_noise"]) == pytest.approx(want["median"] / want["noise"], rel=1.5e-3)
        assert float(got["tensor_noise_T_per_m"]) == pytest.approx(want["tensor"], rel=1e-9)
        assert float(rows[name]["tmi_median_T"]) == pytest.approx(float(got["tmi_median_T"]), rel=1e-8)
        assert medians[name] == pytest.approx(float(got["tmi_median_noise"]), rel=1e-12)
        assert rows[name]["calibration"] == str(campaign["cal"])
    assert int(dom.rows["auv2/m1.csv"]["drops"]) == 1, "the repeated CSV row is a drop"
    assert "4 repeated stamps dropped" in rows["auv2/m1.csv"]["notes"], "its note: one message per sensor"
    assert int(dom.rows["auv1/m1_bag"]["drops"]) == 0
    # Against the truth: a calibration that holds leaves Gaussian noise, |x| median 0.674 sigma; a hard-iron
    # change of DRIFT leaves |DRIFT cos(angle)|, angle uniform over the sphere: median DRIFT/2, p95 0.95 DRIFT.
    for name in ("auv1/m1_bag", "auv2/m1.csv"):
        assert float(dom.rows[name]["tmi_median_noise"]) == pytest.approx(0.674, rel=0.15)
    assert float(dom.rows["auv1/m2_bag"]["tmi_median_T"]) == pytest.approx(DRIFT / 2, rel=0.2)
    assert float(dom.rows["auv1/m2_bag"]["tmi_p95_T"]) == pytest.approx(0.95 * DRIFT, rel=0.1)
    # The drift shows in auv1's trend: first -> last median in noise units grows over tenfold.
    assert float(dom.vehicles["auv1"]["tmi_median_noise"]) > 10
    assert dom.rows[CORRUPT]["status"] == "failed" and CORRUPT not in medians
    # The drifted recording (median about 10 noise sd) is flagged, the others are not.
    assert dom.lists["flagged"] == ["auv1/m2_bag"] and "flagged" in dom.classes["auv1/m2_bag"]
    assert rows["auv1/m2_bag"]["flag"].endswith("far above the floor (flagged over 5x)")
    assert [n for n in GOOD if rows[n]["flag"]] == ["auv1/m2_bag"]


def test_a_rerun_skips_finished_work(campaign: dict[str, Path], dask_cluster: DaskCluster, tmp_path: Path) -> None:
    camp = tmp_path / "campaign"
    for name in ("auv1/m1_bag", "auv2/m1.csv"):
        src = campaign["campaign"] / name
        (camp / name).parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, camp / name)
    out = tmp_path / "out"
    import socket

    with socket.socket() as taken:  # Dask's default HTTP port in use elsewhere must not matter (nor warn)
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            taken.bind(("0.0.0.0", 8787))
            taken.listen()
        except OSError:
            pass  # already taken: the same situation
        first = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--workers", "2"))  # the local cluster
    assert "2 corrected, 0 skipped, 0 failed" in first.stdout
    assert first.stderr == "", first.stderr

    def state() -> dict[str, tuple[int, int]]:
        return {str(p.relative_to(out)): (p.stat().st_ino, p.stat().st_mtime_ns)
                for p in out.rglob("*") if p.is_file() and not p.name.startswith("report.")}

    before = state()
    second = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    assert "0 corrected, 2 skipped, 0 failed" in second.stdout and "--force" in second.stdout
    assert state() == before, "nothing rewritten"
    with open(out / "report.csv", newline="") as fh:
        rows = {r["recording"]: r for r in csv.DictReader(fh)}
    assert {r["status"] for r in rows.values()} == {"skipped"} and all(int(r["sets"]) > 0 for r in rows.values())
    # An input newer than its output is done again; the other is still skipped.
    csv_in = camp / "auv2" / "m1.csv"
    st = csv_in.stat()
    os.utime(csv_in, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    third = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    assert "1 corrected, 1 skipped, 0 failed" in third.stdout
    assert "corrected auv2/m1.csv" in third.stdout
    # An output removed (or damaged) is done again.
    shutil.rmtree(out / "auv1" / "m1_bag")
    fourth = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    assert "1 corrected, 1 skipped, 0 failed" in fourth.stdout and "corrected auv1/m1_bag" in fourth.stdout
    # --force redoes everything.
    fifth = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address, "--force"))
    assert "2 corrected, 0 skipped, 0 failed" in fifth.stdout


def test_calibrate_first_from_each_recordings_own_manoeuvre(
        campaign: dict[str, Path], dask_cluster: DaskCluster, tmp_path: Path) -> None:
    camp = tmp_path / "in"
    camp.mkdir()
    shutil.copy2(campaign["rotation"], camp / "rotation.csv")
    out = tmp_path / "out"
    proc = ok(magcal("batch", camp, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address,
                     "--calibrate", "--reference-field", F))
    own = out / "rotation.csv.calibration.yaml"
    assert own.is_file() and "corrected rotation.csv" in proc.stdout
    ok(magcal("correct", camp / "rotation.csv", "-c", own, "-o", tmp_path / "alone.csv"))
    assert (out / "rotation.csv").read_bytes() == (tmp_path / "alone.csv").read_bytes()
    with open(out / "report.csv", newline="") as fh:
        row = next(csv.DictReader(fh))
    assert row["calibration"] == str(own)
    assert float(row["tmi_median_noise"]) == pytest.approx(0.674, rel=0.15), "its own calibration holds"


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_stops_the_batch_closes_its_workers_and_leaves_no_partial_output(
        campaign: dict[str, Path], tmp_path: Path, signum: signal.Signals, code: int) -> None:
    """Ctrl-C (SIGINT) or a service manager's SIGTERM to the whole process group while tasks write: the
    batch names the signal it got, exits 128 + its number, and leaves no partial output and no worker."""
    import psutil

    camp = tmp_path / "in"
    write_recording_bag(camp / "long_bag", recording(T0, 60_000), "sqlite3")
    write_recording_bag(camp / "long2_bag", recording(T0 + DAY, 60_000), "sqlite3")
    out = tmp_path / "out"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "magcal_ros.app.cli", "batch", str(camp), "-c", str(campaign["cal"]),
                             "-o", str(out), "--workers", "2"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not (out.exists() and any(p.name.endswith(".partial") for p in out.iterdir())):
            assert proc.poll() is None and time.monotonic() < deadline, "no task started writing"
            time.sleep(0.02)
        os.killpg(proc.pid, signum)  # what a terminal's Ctrl-C does: the whole process group
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == code, err
    assert err.strip().splitlines() == [f"magcal batch: stopped by {signum.name}; unfinished output removed"], err
    assert not [p for p in out.rglob("*") if ".partial" in p.name], "no partial output left"
    for name in ("long_bag", "long2_bag"):  # an output is there complete (renamed into place whole) or not at all;
        # the Ctrl-C may land between a task's output and its record: a re-run then redoes that one
        assert not (out / name).exists() or (out / name / "metadata.yaml").exists(), name
    deadline = time.monotonic() + 30
    while True:
        left = [p for p in psutil.process_iter(["pid", "status"])
                if _session(p.pid) == proc.pid and p.info["status"] != psutil.STATUS_ZOMBIE]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert left == [], f"worker processes left running: {left}"


def test_dask_logs_nothing_after_the_local_cluster_closed() -> None:
    """After a batch on a local cluster returns (or is stopped), a log line Dask's client thread emits
    as its connection closes reaches nobody: the batch's stop line stays the last and only line
    (``LocalCluster`` quiets Dask only until it closes; a traceback at INFO had followed the stop line)."""
    code = ("import logging, sys\n"
            "from magcal_ros.app.batch import run_on_dask\n"
            "print(run_on_dask([], 1, None, lambda o: None), file=sys.stdout)\n"
            "try:\n"
            "    raise ConnectionError('closed')\n"
            "except ConnectionError:\n"
            "    logging.getLogger('distributed.batched').info('Batched Comm Closed', exc_info=True)\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "1 local worker process"
    assert done.stderr == ""


def _session(pid: int) -> int | None:
    try:
        return os.getsid(pid)
    except OSError:
        return None


class FakeScheduler:
    """A TCP server on localhost that is not a Dask scheduler: ``http`` answers what it is sent with an
    HTTP 400 and closes (as a web server does), ``silent`` accepts and says nothing, ``garbage`` sends
    random bytes. Counts the connections it accepted."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self.accepted = 0
        self.server = socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.server.getsockname()[1]}"
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.accepted += 1
            self.conns.append(conn)
            threading.Thread(target=self._answer, args=(conn,), daemon=True).start()

    def _answer(self, conn: socket.socket) -> None:
        try:
            if self.mode == "http":
                conn.recv(65536)
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                conn.close()
            elif self.mode == "garbage":
                conn.sendall(np.random.default_rng(1).bytes(4096))
        except OSError:
            pass

    def close(self) -> None:
        self.server.close()
        for conn in self.conns:
            conn.close()


def batch_process(*args: object) -> subprocess.Popen[str]:
    """``magcal batch ARGS`` started in its own session (killed with its children when a test fails)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.Popen([sys.executable, "-m", "magcal_ros.app.cli", "batch", *map(str, args)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(proc: subprocess.Popen[str], deadline: float) -> tuple[str, str]:
    """stdout and stderr of ``proc`` once it ends; it and its children killed if it is not over within
    ``deadline`` s (a hang: the test fails)."""
    try:
        return proc.communicate(timeout=deadline)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"still running after {deadline:g} s (killed): {err[-2000:]}")


@pytest.mark.parametrize(("mode", "reason"), [
    ("http", "answered, but not as a Dask scheduler: its reply is not Dask's protocol"),
    ("garbage", "answered, but not as a Dask scheduler: its reply is not Dask's protocol"),
    ("silent", "no Dask scheduler answered at {address} within 3 s"),
    ("closed", "cannot reach the Dask scheduler at {address}: Connection refused"),
])
def test_a_scheduler_address_that_is_not_dask_is_refused_in_one_line(
        campaign: dict[str, Path], tmp_path: Path, mode: str, reason: str) -> None:
    """A web server, a port that accepts and says nothing, one that sends random bytes, one where nothing
    listens: each is one line and exit 2, nothing run, within a bounded time (Dask's own handshake waits
    for ever on a silent port; an HTTP reply read as Dask's frame header asked for exabytes)."""
    server = FakeScheduler(mode) if mode != "closed" else None
    if server is None:
        with socket.socket() as unused:  # a port nothing listens on
            unused.bind(("127.0.0.1", 0))
            address = f"tcp://127.0.0.1:{unused.getsockname()[1]}"
    else:
        address = server.address
    out = tmp_path / "out"
    try:
        # Only the silent port waits out its timeout; the others answer at once, however busy the machine.
        proc = batch_process(campaign["campaign"] / "auv1", "-c", campaign["cal"], "-o", out, "--scheduler", address,
                             "--connect-timeout", "3" if mode == "silent" else "100")
        _, err = finish(proc, 200)
    finally:
        if server is not None:
            server.close()
    assert proc.returncode == 2, err
    assert err.splitlines() == [err.strip()] and err.startswith("magcal batch: error: "), err
    assert reason.format(address=address) in err and address in err, err
    assert not out.exists(), "nothing run, nothing written"
    assert server is None or server.accepted >= 1


def test_a_dask_worker_is_not_taken_for_the_scheduler(
        campaign: dict[str, Path], dask_cluster: DaskCluster, tmp_path: Path) -> None:
    worker = dask_cluster.worker_addresses[0]
    proc = magcal("batch", campaign["campaign"] / "auv1", "-c", campaign["cal"], "-o", tmp_path / "out",
                  "--scheduler", worker, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip() == (f"magcal batch: error: {worker} is a Dask Worker, not a Dask scheduler: give the "
                                   "scheduler's address"), proc.stderr


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stop_signal_while_connecting_ends_the_batch_at_once(
        campaign: dict[str, Path], tmp_path: Path, signum: signal.Signals, code: int) -> None:
    """A scheduler that accepts and never answers, a connect timeout of ten minutes: SIGTERM (or Ctrl-C)
    while the batch waits on it ends the batch with 128 + the signal and its one line (it ignored both
    for 14 minutes)."""
    server = FakeScheduler("silent")
    try:
        proc = batch_process(campaign["campaign"] / "auv1", "-c", campaign["cal"], "-o", tmp_path / "out",
                             "--scheduler", server.address, "--connect-timeout", "600")
        deadline = time.monotonic() + 120
        while server.accepted < 1:
            assert proc.poll() is None and time.monotonic() < deadline, "the batch never connected"
            time.sleep(0.05)
        os.kill(proc.pid, signum)
        _, err = finish(proc, 60)
    finally:
        server.close()
    assert proc.returncode == code, err
    assert err.strip().splitlines() == [f"magcal batch: stopped by {signum.name}; unfinished output removed"], err


def test_more_local_workers_than_the_machine_runs_are_refused_before_anything_starts(
        campaign: dict[str, Path], tmp_path: Path) -> None:
    """``--workers 1000000`` grew to 3.6 GB in 10 minutes without starting a worker: refused at once."""
    from magcal_ros.app.batch import max_workers

    limit, _ = max_workers()
    out = tmp_path / "out"
    proc = batch_process(campaign["campaign"] / "auv1", "-c", campaign["cal"], "-o", out, "--workers", "1000000")
    _, err = finish(proc, 60)
    assert proc.returncode == 2, err
    assert err.strip().splitlines() == [f"magcal batch: error: --workers 1000000: this machine runs at most {limit} "
                                        f"local worker processes ({max_workers()[1]}); give at most {limit}"], err
    assert not out.exists()


def _outcome(name: str, day: int, ratio: float, vehicle: str = "auv1") -> Any:
    """A corrected recording whose median TMI residual is ``ratio`` noise sd (noise 1 nT)."""
    from magcal_ros.app.campaign import Outcome

    start = int((T0 + day * DAY) * 1e9)
    return Outcome(name, vehicle, "corrected", f"/in/{name}", f"/out/{name}", "/cal.yaml", sets=SETS, drops=0,
                   start_ns=start, end_ns=start + 30 * 10**9, intensity=F, noise=NOISE, tmi_median=ratio * NOISE,
                   tmi_p95=3 * ratio * NOISE, tensor_noise=3.5 * NT * (1 + ratio / 100))


def test_one_recording_far_above_the_floor_neither_flattens_the_others_nor_passes_unflagged(tmp_path: Path) -> None:
    """Seven recordings at 0.6-0.8 noise sd and one at 1,265: on the report's linear axes the seven lay
    flat on zero and the bad one was a plain "corrected". Now the axes are logarithmic (each point where
    log10 puts it, the seven spread as their values differ, on the dashed noise-floor line), and the bad
    one is flagged, the threshold stated, in the page, the CSV and the batch's lines."""
    from magcal_ros.app import batch_report

    good = [_outcome(f"m{k}.csv", k, r) for k, r in enumerate((0.60, 0.63, 0.66, 0.69, 0.72, 0.76, 0.80))]
    bad = _outcome("m9.csv", 9, 1265.0)
    page = tmp_path / "report.html"
    batch_report.write_html(page, [*good, bad], str(tmp_path))
    batch_report.write_csv(tmp_path / "report.csv", [*good, bad])
    dom = DomTables()
    dom.feed(page.read_text())
    chart = dom.charts["TMI residual, median"]
    lo, hi, top, height = (float(chart[k]) for k in ("data-lo", "data-hi", "data-top", "data-height"))
    assert chart["data-scale"] == "log" and 10**lo <= 0.6 and 10**hi >= 1265
    ys = dom.ys["TMI residual, median"]
    for o in [*good, bad]:
        want = top + height * (1 - (np.log10(o.tmi_median / NOISE) - lo) / (hi - lo))
        assert ys[o.name] == pytest.approx(want, abs=0.06), o.name
    spread = ys["m0.csv"] - ys["m6.csv"]
    assert spread > 0.1 * height / (hi - lo), "0.6 .. 0.8 spread over a tenth of a decade, not flattened"
    assert ys["m0.csv"] > ys["floor"] > ys["m6.csv"], "the floor (0.6745) among them"
    assert ys["m6.csv"] > ys["flag"] > ys["m9.csv"], "the flag threshold between them and the bad one"
    # Flagged, with its threshold, in the page and the CSV; the others not.
    assert dom.lists["flagged"] == ["m9.csv"] and dom.classes["m9.csv"] == "corrected flagged"
    assert all(dom.classes[o.name] == "corrected" for o in good)
    with open(tmp_path / "report.csv", newline="") as fh:
        flags = {r["recording"]: r["flag"] for r in csv.DictReader(fh)}
    assert flags.pop("m9.csv") == "TMI median 1.26e+03x the noise: far above the floor (flagged over 5x)"
    assert set(flags.values()) == {""}
    assert 'data-flagged="1"' in page.read_text()


_OVERLAPS = """<script>
(function(){
  var found = [];
  document.querySelectorAll('svg.chart').forEach(function(svg){
    var boxes = Array.prototype.map.call(svg.querySelectorAll('text'), function(t){
      return [t.getBoundingClientRect(), t.textContent]; });
    for (var i = 0; i < boxes.length; i++) { for (var j = i + 1; j < boxes.length; j++) {
      var a = boxes[i][0], b = boxes[j][0];
      if (a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom) {
        found.push(svg.getAttribute('data-title') + ': ' + boxes[i][1] + ' / ' + boxes[j][1]); } } }
  });
  document.documentElement.setAttribute('data-texts', String(document.querySelectorAll('svg.chart text').length));
  document.documentElement.setAttribute('data-overlaps', JSON.stringify(found));
})();
</script></body>"""


@pytest.mark.parametrize("span_days", [0.01, 0.5, 3.0, 40.0, 900.0])
def test_no_label_of_the_reports_charts_overlaps_another_in_a_browser(tmp_path: Path, span_days: float) -> None:
    """The date labels of the time axes overlapped. Every text of every chart (title, value and time axis
    labels, the reference lines' labels, the legend), measured where Chromium lays it out, overlaps no
    other: campaigns of a quarter of an hour to two and a half years, three vehicles with long names."""
    from magcal_ros.app import batch_report

    outcomes = [_outcome(f"{v}/m{k}.csv", int(0), 0.7 + 0.01 * k + 400 * (k == 7), vehicle=v)
                for v in ("auv_long_name_one", "glider_second_vehicle", "auv3") for k in range(9)]
    outcomes = [replace_start(o, int((T0 + span_days * DAY * k / 26) * 1e9)) for k, o in enumerate(outcomes)]
    page = tmp_path / "report.html"
    batch_report.write_html(page, outcomes, str(tmp_path))
    page.write_text(page.read_text().replace("</body>", _OVERLAPS))
    dom = chromium_dom(page)
    texts = int(dom.split('data-texts="', 1)[1].split('"', 1)[0])
    overlaps = html.unescape(dom.split('data-overlaps="', 1)[1].split('"', 1)[0])
    assert texts > 40, "every chart's labels measured"
    assert json.loads(overlaps) == []


def replace_start(o: Any, start_ns: int) -> Any:
    """``o`` starting at ``start_ns``."""
    from dataclasses import replace

    return replace(o, start_ns=start_ns, end_ns=start_ns + 30 * 10**9)


def test_one_report_for_one_directorys_outputs_whatever_runs_wrote_them(
        campaign: dict[str, Path], dask_cluster: DaskCluster, tmp_path: Path) -> None:
    """Two batches of different inputs into one OUTDIR: the report of the second lists the first's outputs
    too (it listed only its own); an output removed since is no longer listed. The second campaign's
    folder holds a stray .db3 and a note beside its CSV: the CSV is corrected, the two are listed as
    skipped (the .db3 made the folder one failed bag, its CSV never tried)."""
    first_in, second_in, out = tmp_path / "first", tmp_path / "second", tmp_path / "out"
    for name in ("auv1/m1_bag", "auv2/m1.csv"):
        src = campaign["campaign"] / name
        (first_in / name).parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, first_in / name)
    (second_in / "auv3").mkdir(parents=True)
    write_csv(second_in / "auv3" / "m3.csv", recording(T0 + 5 * DAY))
    (second_in / "auv3" / "stray_0.db3").write_bytes(b"SQLite format 3\x00" + bytes(100))
    (second_in / "auv3" / "notes.txt").write_text("dive log\n")
    ok(magcal("batch", first_in, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    second = ok(magcal("batch", second_in, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    assert "batch: 1 recording: 1 corrected, 0 skipped, 0 failed" in second.stdout, second.stdout
    assert "(with 2 more recordings earlier runs wrote there)" in second.stdout
    assert "note: 2 files found that are not a recording, skipped (listed in the report): auv3/notes.txt, " \
           "auv3/stray_0.db3" in second.stderr

    def report() -> dict[str, dict[str, str]]:
        with open(out / "report.csv", newline="") as fh:
            return {r["recording"]: r for r in csv.DictReader(fh)}

    rows = report()
    assert {n: r["status"] for n, r in rows.items()} == {
        "auv1/m1_bag": "skipped", "auv2/m1.csv": "skipped", "auv3/m3.csv": "corrected",
        "auv3/notes.txt": "skipped", "auv3/stray_0.db3": "skipped"}
    assert int(rows["auv1/m1_bag"]["sets"]) == SETS and int(rows["auv3/m3.csv"]["sets"]) == SETS
    assert rows["auv3/stray_0.db3"]["reason"].startswith("not a recording: a rosbag2 storage file without")
    assert rows["auv3/notes.txt"]["reason"] == "not a recording: neither a .csv file nor a rosbag2 directory"
    dom = DomTables()
    dom.feed((out / "report.html").read_text())
    assert set(dom.rows) == {"auv1/m1_bag", "auv2/m1.csv", "auv3/m3.csv"}
    assert dom.lists["others"] == ["auv3/notes.txt", "auv3/stray_0.db3"]
    # An output removed is no longer the directory's: the next report leaves it out.
    shutil.rmtree(out / "auv1" / "m1_bag")
    third = ok(magcal("batch", second_in, "-c", campaign["cal"], "-o", out, "--scheduler", dask_cluster.address))
    assert "(with 1 more recording earlier runs wrote there)" in third.stdout
    assert set(report()) == {"auv2/m1.csv", "auv3/m3.csv", "auv3/notes.txt", "auv3/stray_0.db3"}


def test_an_output_directory_that_cannot_be_written_is_refused_before_any_task_runs(
        campaign: dict[str, Path]) -> None:
    """A read-only OUTDIR ran every task before failing with exit 2: now one line, nothing run. As root the
    batch runs without the capability to override file permissions (root writes anywhere)."""
    import stat

    shared = Path(tempfile.mkdtemp(prefix="magcal_readonly_"))
    try:
        shutil.copytree(campaign["campaign"] / "auv1", shared / "in")
        shutil.copy2(campaign["cal"], shared / "cal.yaml")
        out = shared / "out"
        out.mkdir()
        for p in [shared, *shared.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
        out.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP | stat.S_IROTH | stat.S_IXOTH)  # r-x
        env = dict(os.environ, HOME=str(shared))
        env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")

        def unprivileged() -> None:
            if os.geteuid() == 0:  # drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH from what the batch gets
                import ctypes

                libc = ctypes.CDLL(None, use_errno=True)
                for cap in (1, 2):
                    if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
                        os._exit(99)

        proc = subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", "batch", str(shared / "in"), "-c",
                               str(shared / "cal.yaml"), "-o", str(out), "--workers", "1"], env=env,
                              capture_output=True, text=True, timeout=300, preexec_fn=unprivileged)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert proc.stderr.strip() == (f"magcal batch: error: output directory {out} cannot be written ({out}: "
                                       "Permission denied); nothing run"), proc.stderr
        assert proc.stdout == "", "no task ran"
        assert list(out.iterdir()) == []
    finally:
        shared.chmod(0o755)
        (shared / "out").chmod(0o755)
        shutil.rmtree(shared, ignore_errors=True)
