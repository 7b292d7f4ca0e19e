"""``magcal batch``: a campaign's recordings corrected at once on Dask, with a campaign report.

Each recording is one Dask task (:func:`~magcal_ros.app.batch_task.run_job`) that runs
``magcal correct`` on it, so the rules of a single run hold per recording. By default the
tasks run on a local cluster of worker processes (``--workers N``, one thread each);
``--scheduler ADDRESS`` sends them to an existing Dask cluster whose workers see the same
paths. Dask is imported here only when a batch runs, so the other commands do not pay for it.

What is planned, skipped and how recordings are named: :mod:`magcal_ros.app.campaign`;
the report: :mod:`magcal_ros.app.batch_report`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from magcal_ros.errors import InputError, MagcalError, Stopped

if TYPE_CHECKING:
    from magcal_ros.app.campaign import Found, Job, Outcome
    from magcal_ros.app.progress import ProgressBar

EPILOG_BATCH = """examples:
  magcal batch campaign/ -c cal.yaml -o corrected/               # every bag and CSV below campaign/
  magcal batch a_bag b_bag c.csv -c cal.yaml -o out/ --workers 2
  magcal batch @missions.txt -c calibrations.yaml -o out/        # a list file and a mapping file
  magcal batch campaign/ -c cal.yaml -o out/ --scheduler tcp://10.0.0.5:8786   # an existing Dask cluster
  magcal batch campaign/ -c cal.yaml -o out/ --force             # redo recordings already done
  magcal batch campaign/ -c prior.yaml -o out/ --calibrate --reference-field 5.15e-5

inputs: rosbag2 directories (a directory is a bag only by its metadata.yaml) and .csv files; any
other directory is walked: every recording below it (hidden entries and OUTDIR left out), its
output at OUTDIR/<path relative to the walked directory>; the other files found there (notes, a
stray .db3 without its metadata.yaml) are listed in the report as skipped, never run. A
recording named directly goes to OUTDIR/<its name>. @FILE or --list FILE: one path per line
(# comments; relative to FILE). OUTDIR is created and checked writable before anything runs.

calibration (-c): one calibration file for every recording, or a mapping file:
  magcal_batch:
    calibrations:                       # the first entry that matches wins
      - {vehicle: auv1, calibration: auv1.yaml}
      - {match: "glider*/2025-*", calibration: glider_2025.yaml}
      - {calibration: default.yaml}     # no condition: any recording
  vehicle: glob over the recording's vehicle; match: glob over its name under OUTDIR or its
  absolute path ('*' crosses '/'); paths relative to the mapping file. A recording no entry
  covers fails with that reason.
vehicle: the directory holding the recording (campaign/auv1/m1_bag: auv1), or with
  --vehicle-pattern REGEX the group 'vehicle' (else group 1, else the match) of the pattern's
  first match in the recording's absolute path.
--calibrate: calibrate each recording from its own manoeuvre first (magcal calibrate, with the
  mapped calibration as --prior when there is one), written to OUTDIR/<name>.calibration.yaml,
  then correct with it; a recording whose manoeuvre is refused fails with the reason.

per recording: exactly 'magcal correct' (same outputs, stamps, refusals, atomic writes). A
recording that fails is reported by name with its one-line reason; the others go on. Done
recordings are recorded in OUTDIR/.magcal_batch/; a re-run skips those whose input, output,
calibration and options are unchanged (--force redoes them).

report: OUTDIR/report.csv and OUTDIR/report.html (self-contained: inline SVG, no external
files), one report for everything in OUTDIR: this run's recordings and every output an earlier
run (of any inputs) wrote there that is still as written. Per recording sets, drops, time span,
TMI residual | |B| - F | (median, 95th percentile, and both over the calibration's noise),
tensor noise, the calibration used; per vehicle their trend over time on logarithmic axes with
the noise floor; a recording whose median is over 5 noise sd is flagged (FLAGGED on its line,
the report's flag column and list).

Dask: --workers N local worker processes (at most 4 per core, fewer when the available memory
holds fewer of 256 MiB; never fewer than the cores). --scheduler ADDRESS must answer as a Dask
scheduler within --connect-timeout seconds (default 20), each step bounded: the TCP connection,
Dask's handshake and first reply, the client's own connection; a web server, a silent port or
anything else that is not a Dask scheduler is one line, exit 2, nothing run. Stop signals are
taken at every stage, connecting included.

exit codes: 0 every recording done (corrected now or skipped); 1 some failed (the report names
them); 2 the batch refused (bad option, calibration, mapping or scheduler; nothing run);
130, 143, 129 stopped by SIGINT, SIGTERM, SIGHUP (the line names the signal)."""


WORKER_START_TIMEOUT = 300.0
"""Seconds the local cluster's workers may take to start (imports on a loaded machine)."""
CONNECT_TIMEOUT = 20.0
"""Default seconds a Dask scheduler has to answer (``--connect-timeout``): each of the TCP connection,
Dask's handshake and the first reply, and the client's own connection."""


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError("at least 1 worker")
    return n


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (0 < value <= 86_400):
        raise argparse.ArgumentTypeError("between 0 and 86400 seconds")
    return value


def default_workers() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


WORKERS_PER_CORE = 4
"""At most this many local worker processes per core: a task is one single-threaded ``magcal correct``."""
WORKER_MEMORY = 256 * 2**20
"""Bytes a local worker process needs at least (Python with numpy, Dask and one streaming correction)."""


def available_memory() -> int | None:
    """Bytes of memory available to new processes (``MemAvailable``), or None when unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return None


def max_workers() -> tuple[int, str]:
    """The most local worker processes this machine runs, and why: :data:`WORKERS_PER_CORE` per core,
    fewer when the available memory holds fewer of :data:`WORKER_MEMORY`, never fewer than the cores."""
    cores = default_workers()
    limit, why = WORKERS_PER_CORE * cores, f"{WORKERS_PER_CORE} per core on its {cores} core{'s' if cores != 1 else ''}"
    memory = available_memory()
    if memory is not None and memory // WORKER_MEMORY < limit:
        limit = max(cores, int(memory // WORKER_MEMORY))
        why = (f"{WORKER_MEMORY / 2**20:.0f} MiB each of its {memory / 2**30:.1f} GiB available memory, "
               f"at least one per core")
    return limit, why


def add_batch_parser(sub: argparse._SubParsersAction, make: Callable[..., argparse.ArgumentParser]) -> None:  # type: ignore[type-arg]
    """Add ``magcal batch`` to ``sub``; ``make`` is the CLI's subcommand factory."""
    from magcal_ros.app.commands import common

    p = make(
        sub, "batch", "correct a campaign's recordings at once (Dask), with a campaign report",
        "Correct many recordings (bags and CSVs, directories walked, list files) each with its calibration, "
        "one Dask task per recording on a local cluster or an existing one, and write a campaign report.",
        EPILOG_BATCH,
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recordings (rosbag2 directory or .csv), directories to walk, or @LISTFILE")
    p.add_argument("-c", "--calibration", required=True, metavar="CAL.yaml",
                   help="calibration file for every recording, or a mapping file (magcal_batch: calibrations: ...)")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="output directory (created)")
    p.add_argument("--list", action="append", metavar="FILE", help="a list file: one recording or directory per line")
    g = p.add_argument_group("Dask")
    g.add_argument("--workers", type=_workers, metavar="N",
                   help=f"worker processes of the local cluster, one thread each (default: the cores, {default_workers()}; "
                   f"at most {WORKERS_PER_CORE} per core, fewer when memory is short)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on an existing Dask cluster (e.g. tcp://host:8786) whose workers see the same paths")
    g.add_argument("--connect-timeout", type=_seconds, metavar="SECONDS",
                   help="seconds the --scheduler has to answer as a Dask scheduler, handshake included "
                   f"(default {CONNECT_TIMEOUT:g})")
    g = p.add_argument_group("campaign")
    g.add_argument("--force", action="store_true", help="redo recordings a previous run finished")
    g.add_argument("--vehicle-pattern", metavar="REGEX",
                   help="find each recording's vehicle in its absolute path (group 'vehicle', else group 1, else the "
                   "match); default: the directory holding the recording")
    g.add_argument("--calibrate", action="store_true",
                   help="calibrate each recording from its own manoeuvre first (the mapped calibration as prior)")
    g.add_argument("--reference-field", type=float, default=None, metavar="TESLA",
                   help="total intensity F (T): for --calibrate, and the F of the report's TMI residual "
                   "(default: the calibration's)")
    g.add_argument("--site", metavar="LAT,LON[,ALT_M]", help="--calibrate: F from the World Magnetic Model at this site")
    g.add_argument("--date", metavar="YYYY-MM-DD", help="--calibrate: date for --site (default today, UTC)")
    g = p.add_argument_group("correction (as magcal correct)")
    g.add_argument("--uncorrected", metavar="NAME[,NAME]", help="sensors the calibration may lack a block for")
    g.add_argument("--storage", choices=["sqlite3", "mcap"], help="output storage of bag inputs (default: the input's)")
    g.add_argument("--frame-id", default=None, help="platform frame of the outputs (default magcal_array)")
    g.add_argument("--gradient-method", default=None, choices=["difference", "least_squares"],
                   help="as magcal correct (default: difference for the cross, least_squares otherwise)")
    copy = g.add_mutually_exclusive_group()
    copy.add_argument("--copy-topics", metavar="T1,T2", help="bag inputs: also copy these topics unchanged")
    copy.add_argument("--copy-all", action="store_true", help="bag inputs: also copy every topic unchanged")
    common.add_sync_options(g)
    common.add_current_options(g)
    common.add_temperature_options(g)
    common.add_common_options(p)
    p.set_defaults(func=cmd_batch)


def _common_options(args: argparse.Namespace, bag: bool) -> list[str]:
    """Synchronisation, non-finite and side-stream options ``correct`` and ``calibrate`` share (only those given)."""
    from magcal_ros.core.sync import DEFAULT_MAX_GAP, DEFAULT_SYNC_MODE, DEFAULT_SYNC_TOLERANCE
    from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE

    common: list[str] = []
    if args.sync_tolerance != DEFAULT_SYNC_TOLERANCE:
        common += ["--sync-tolerance", repr(args.sync_tolerance)]
    if args.sync_mode != DEFAULT_SYNC_MODE:
        common += ["--sync-mode", args.sync_mode]
    if args.max_gap != DEFAULT_MAX_GAP:
        common += ["--max-gap", repr(args.max_gap)]
    if bag and args.temperature_topics:
        common += ["--temperature-topics", args.temperature_topics]
    if bag and args.temperature_tolerance != DEFAULT_TEMPERATURE_TOLERANCE:
        common += ["--temperature-tolerance", repr(args.temperature_tolerance)]
    if args.drop_nonfinite:
        common.append("--drop-nonfinite")
    if bag and args.currents:
        common += ["--currents", args.currents, "--current-tolerance", repr(args.current_tolerance)]
    return common


def _correct_only_options(args: argparse.Namespace, bag: bool) -> list[str]:
    """Options only ``magcal correct`` takes (the bag-only ones for bags only)."""
    out: list[str] = []
    if args.uncorrected:
        out += ["--uncorrected", args.uncorrected]
    if args.frame_id is not None:
        out += ["--frame-id", args.frame_id]
    if args.gradient_method is not None:
        out += ["--gradient-method", args.gradient_method]
    if bag and args.storage:
        out += ["--storage", args.storage]
    if bag and args.copy_topics:
        out += ["--copy-topics", args.copy_topics]
    if bag and args.copy_all:
        out.append("--copy-all")
    return out


def _options(args: argparse.Namespace, bag: bool) -> tuple[list[str], list[str]]:
    """``magcal correct`` and ``magcal calibrate`` options of one recording (only those given)."""
    common = _common_options(args, bag)
    calibrate = list(common)
    if args.reference_field is not None:
        calibrate += ["--reference-field", repr(args.reference_field)]
    if args.site is not None:
        calibrate += [f"--site={args.site}"] + (["--date", args.date] if args.date else [])
    return common + _correct_only_options(args, bag), calibrate


def _check_options(args: argparse.Namespace) -> None:
    """Refuse option combinations and values no batch can use (:class:`InputError`, one line)."""
    if args.scheduler and args.workers:
        raise InputError("--workers sizes the local cluster; with --scheduler the cluster's own workers run the tasks")
    if args.connect_timeout is not None and not args.scheduler:
        raise InputError("--connect-timeout applies to --scheduler")
    if args.workers:
        limit, why = max_workers()
        if args.workers > limit:
            raise InputError(f"--workers {args.workers}: this machine runs at most {limit} local worker processes "
                             f"({why}); give at most {limit}")
    if (args.site or args.date) and not args.calibrate:
        raise InputError("--site and --date apply to --calibrate")
    if args.site and args.reference_field is not None:
        raise InputError("give either --reference-field or --site, not both")
    if args.reference_field is not None and not (1e-7 <= args.reference_field <= 1e-3):
        raise InputError(f"--reference-field {args.reference_field:g} T is not Earth-like (1e-7 .. 1e-3 T)")


def _recordings(args: argparse.Namespace, outdir: Path) -> tuple[list[tuple[str, Path]], Found]:
    """The recordings the inputs name, ``(name under OUTDIR, path)`` once each, and all that was found;
    refused when there are none, two would write one name, or one would take a name the batch keeps
    for itself."""
    from magcal_ros.app import campaign as cp

    found = cp.find_recordings(args.inputs, args.list or [], outdir.resolve())
    unique: list[tuple[str, Path]] = []
    seen: set[tuple[str, Path]] = set()
    for name, path in found.recordings:
        if (name, path.resolve()) not in seen:
            seen.add((name, path.resolve()))
            unique.append((name, path))
    clash = cp.duplicates(unique)
    if clash:
        more = f" (and {len(clash) - 3} more)" if len(clash) > 3 else ""
        raise InputError("; ".join(clash[:3]) + more + ": give their parent directory instead (a walk keeps "
                         "relative names)")
    if not unique:
        others = f"; {len(found.others)} other file{'s' if len(found.others) != 1 else ''}" if found.others else ""
        raise InputError(f"no recordings in {' '.join(args.inputs + (args.list or []))} (rosbag2 directories with "
                         f"their metadata.yaml, or .csv files{others})")
    bad = [n for n, _ in unique if cp.reserved(n)]
    if bad:
        raise InputError(f"recording {bad[0]} would write over the batch's own {bad[0]} in OUTDIR: rename it")
    return unique, found


def _problem(path: Path, calibration: Path | None, missing: Callable[[], str], calibrate: bool) -> str:
    """Why the recording at ``path`` cannot run at all ('' when it can)."""
    from magcal_ros.app import campaign as cp

    if not path.exists():
        return f"{path} does not exist"
    if not (cp.is_bag_dir(path) or cp.is_csv_path(path) or path.suffix in cp.STORAGE_SUFFIXES):
        return f"{path}: not a recording: give a rosbag2 directory or a .csv file"
    if calibration is None and not calibrate:
        return missing()
    return ""


class Plan(NamedTuple):
    """A batch planned: its jobs in input order, notes, and the files found that are not recordings
    (outcomes ``skipped``, :attr:`~magcal_ros.app.campaign.Outcome.other`)."""

    jobs: list[Job]
    notes: list[str]
    others: list[Outcome]


def plan(args: argparse.Namespace) -> Plan:
    """The batch's :class:`Plan`; :class:`InputError` when the batch is refused."""
    from magcal_ros.app import campaign as cp

    _check_options(args)
    outdir = Path(args.output).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"output {args.output} exists and is not a directory")
    unique, found = _recordings(args, outdir)
    cmap = cp.load_calibrations(args.calibration)
    pattern = cp.vehicle_pattern(args.vehicle_pattern)
    uncorrected = tuple(n.strip() for n in (args.uncorrected or "").split(",") if n.strip())
    jobs = []
    for name, path in unique:
        vehicle = cp.vehicle_of(path, pattern)
        cal = cmap.lookup(name, path, vehicle)
        output = outdir / name
        if output.resolve() == path.resolve():
            raise InputError(f"output {output} would overwrite the input {path}: choose another OUTDIR")
        problem = _problem(path, cal, lambda: cmap.missing(name, vehicle), args.calibrate)  # noqa: B023 - called now
        correct, calibrate = _options(args, bag=not cp.is_csv_path(path))
        jobs.append(cp.Job(
            name=name, input=str(path.absolute()), output=str(output), vehicle=vehicle,
            calibration=str(cal.absolute()) if cal is not None else "", record=str(cp.record_path(outdir, name)),
            correct_args=tuple(correct), calibrate_args=tuple(calibrate) if args.calibrate else None,
            calibration_out=str(outdir / f"{name}.calibration.yaml") if args.calibrate else "",
            reference_field=args.reference_field, uncorrected=uncorrected, problem=problem,
        ))
    _check_calibrations(jobs, uncorrected)
    others = [cp.Outcome(name, cp.vehicle_of(path, pattern), "skipped", str(path.absolute()),
                         reason=cp.not_a_recording(path), other=True) for name, path in found.others]
    return Plan(jobs, found.notes, others)


def _check_calibrations(jobs: Sequence[Job], uncorrected: tuple[str, ...]) -> None:
    """Refuse the batch when a calibration file it would use cannot be read (one line naming it)."""
    from magcal_ros.io import calibration_file as calfile

    for path in sorted({j.calibration for j in jobs if j.calibration and not j.problem}):
        try:
            calfile.read(path, uncorrected=uncorrected)
        except InputError as exc:
            raise InputError(exc if path in str(exc) else f"{path}: {exc}") from None


class Console:
    """Per-recording lines and the batch's progress bar on one terminal."""

    def __init__(self, bar: ProgressBar, quiet: bool) -> None:
        self.bar = bar
        self.quiet = quiet

    def line(self, text: str, error: bool = False) -> None:
        stream = sys.stderr if error else sys.stdout
        self.bar.clear()
        if error or not self.quiet:
            print(text, file=stream, flush=True)

    def done(self, o: Outcome) -> None:
        from magcal_ros.core.units import NT

        if o.status == "failed":
            self.line(f"  FAILED {o.name}: {o.reason}", error=True)
            return
        tmi = (f", TMI median {o.tmi_median / NT:.3g} nT" + (f" ({o.ratio(o.tmi_median):.2g}x noise)" if o.noise else "")
               if o.tmi_median is not None else "")
        tensor = f", tensor noise {o.tensor_noise / NT:.3g} nT/m" if o.tensor_noise is not None else ""
        from magcal_ros.app.batch_report import flag_of

        took = f", {o.seconds:.1f} s" if o.seconds is not None and o.status == "corrected" else ""
        flag = f"; FLAGGED: {flag_of(o)}" if flag_of(o) else ""
        self.line(f"  {o.status} {o.name}: {o.sets} sets, {o.drops} dropped{tmi}{tensor}{took}{flag}")


def failure_reason(exc: BaseException) -> str:
    """One line for a task's exception (a refusal's own reason; a lost worker said as such)."""
    from magcal_ros.app.batch_task import RecordingFailed

    if isinstance(exc, RecordingFailed):
        return str(exc)
    kind = type(exc).__name__
    if kind == "KilledWorker":
        return "the worker running it died (killed, or out of memory) every time it was tried"
    text = str(exc).strip().splitlines()
    return f"{kind}: {text[0]}" if text else kind


class StopSignals:
    """While a batch runs, a stop signal (SIGINT, SIGTERM, SIGHUP) only sets a flag; :meth:`check`
    raises it as :class:`~magcal_ros.errors.Stopped` at a point where the cluster can be closed cleanly
    (raising inside Dask's own waits leaves its state broken)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> "StopSignals":
        from magcal_ros.io.atomic import STOP_SIGNALS

        if threading.current_thread() is threading.main_thread():
            self.previous = {s: signal.signal(s, self._note) for s in STOP_SIGNALS}
        return self

    def _note(self, signum: int, frame: object) -> None:
        if self.signum is None:
            self.signum = signum

    def check(self) -> None:
        """Raise ``Stopped`` if a stop signal came."""
        if self.signum is not None:
            raise Stopped(self.signum)

    def __exit__(self, *exc: object) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)


def in_thread(work: Callable[[], Any], seconds: float, stop: StopSignals, name: str) -> Any:
    """``work()`` run in a daemon thread while this one takes stop signals (:meth:`StopSignals.check`,
    every 0.1 s): its result, or what it raised; TimeoutError after ``seconds`` (the thread is left to
    end by itself: what it waits on is bounded too)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["result"] = work()
        except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
            box["error"] = exc

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    deadline = time.monotonic() + seconds
    while thread.is_alive():
        stop.check()
        if time.monotonic() > deadline:
            raise TimeoutError(f"{name}: no result within {seconds:g} s")
        thread.join(0.1)
    stop.check()
    if "error" in box:
        raise box["error"]
    return box.get("result")


def _tcp_location(address: str) -> tuple[str, int] | None:
    """Host and port of a ``tcp://HOST:PORT`` (or ``HOST:PORT``) scheduler address; None for another
    transport (tls://, ucx://, ...); :class:`InputError` for text that is not an address."""
    from distributed.comm import registry
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        registry.get_backend(scheme)  # a transport Dask speaks
        if scheme != "tcp":
            return None
        host, port = parse_host_port(location)
    except (ValueError, TypeError):
        raise InputError(f"--scheduler {address!r} is not an address: give tcp://HOST:PORT") from None
    if not host or not isinstance(port, int) or not 0 < port < 65536:
        raise InputError(f"--scheduler {address!r} is not an address: give tcp://HOST:PORT")
    return host, port


def _scheduler_identity(address: str, timeout: float) -> dict[str, Any]:
    """What the process at ``address`` says it is, asked as Dask asks (handshake, then the ``identity``
    operation), the whole exchange within ``timeout`` s. Raises :class:`InputError` (one line) for an
    address nothing listens on, or a reply that is not Dask's; TimeoutError when no reply comes."""
    import asyncio
    import socket

    from distributed.comm import connect

    location = _tcp_location(address)
    if location is not None:  # a plain TCP connection first: "nothing listens" said at once, not after retries
        try:
            socket.create_connection(location, timeout=timeout).close()
        except OSError as exc:
            reason = exc.strerror or str(exc) or type(exc).__name__
            raise InputError(f"cannot reach the Dask scheduler at {address}: {reason}") from None

    async def ask() -> Any:
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(ask(), timeout))
    except (asyncio.TimeoutError, TimeoutError):
        raise TimeoutError(address) from None
    except Exception as exc:  # noqa: BLE001 - whatever the bytes made of Dask's decoder: not Dask's reply
        raise InputError(f"{address} answered, but not as a Dask scheduler: its reply is not Dask's protocol "
                         f"({type(exc).__name__}); check the address and port") from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        kind = reply.get("type") if isinstance(reply, dict) else None
        what = f"a Dask {kind}" if isinstance(kind, str) and kind else "not a Dask scheduler"
        raise InputError(f"{address} is {what}, not a Dask scheduler: give the scheduler's address")
    return reply


def connect_scheduler(address: str, timeout: float, stop: StopSignals) -> tuple[Any, int]:
    """A client of the Dask scheduler at ``address`` and its worker count. Every step is bounded by
    ``timeout`` s (the TCP connection, Dask's handshake, the first reply, the client's own connection)
    and takes stop signals; :class:`InputError` (one line) when nothing answers as a Dask scheduler."""
    from distributed import Client

    try:
        identity = in_thread(lambda: _scheduler_identity(address, timeout), timeout + 5.0, stop,
                             "magcal-scheduler-probe")
        client = in_thread(lambda: Client(address, timeout=f"{timeout}s"), timeout + 5.0,
                           stop, "magcal-scheduler-client")
    except TimeoutError:
        raise InputError(f"no Dask scheduler answered at {address} within {timeout:g} s (something may accept "
                         "connections there but says nothing Dask says; --connect-timeout waits longer)") from None
    except (OSError, ValueError) as exc:
        text = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise InputError(f"cannot reach the Dask scheduler at {address}: {text}") from None
    return client, len(identity.get("workers") or {})


def _local_cluster(n: int, stop: StopSignals) -> tuple[Any, Any]:
    """A ``LocalCluster`` of ``n`` single-threaded worker processes and its client.

    The worker processes are spawned with SIGINT ignored (a disposition they inherit and
    Python keeps), so a terminal's Ctrl-C, sent to the whole process group, stops only this
    process, which then closes them; this process ignores SIGINT too only until the
    processes exist (a fraction of a second), not during their start-up.
    """
    import logging
    import multiprocessing

    from distributed import Client, LocalCluster

    main = threading.current_thread() is threading.main_thread()
    held = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    cluster = None
    try:
        try:
            # The scheduler's HTTP server on a free local port (the default 8787 may be taken: a warning).
            cluster = LocalCluster(n_workers=0, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                                   silence_logs=logging.CRITICAL)  # a failed task is reported by name instead
            cluster.scale(n)
            deadline = time.monotonic() + WORKER_START_TIMEOUT
            while len(multiprocessing.active_children()) < n and time.monotonic() < deadline:
                stop.check()  # SIGTERM and SIGHUP here; a Ctrl-C only once the workers exist
                time.sleep(0.02)
        finally:
            if main:
                signal.signal(signal.SIGINT, held)
        client = Client(cluster)
        deadline = time.monotonic() + WORKER_START_TIMEOUT
        while len(client.scheduler_info(n_workers=-1).get("workers", {})) < n:
            stop.check()
            if time.monotonic() > deadline:
                raise TimeoutError(f"not up within {WORKER_START_TIMEOUT:.0f} s")
            time.sleep(0.1)
    except (OSError, RuntimeError, TimeoutError) as exc:
        if cluster is not None:
            cluster.close()
        raise MagcalError(f"cannot start a local Dask cluster of {n} workers: {exc}") from None
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise
    return cluster, client


def _quiet_dask_logs() -> None:
    """Dask's own log lines off in this process for good, not only while the cluster lives.

    ``LocalCluster(silence_logs=...)`` quiets Dask's stream handler only until the cluster closes;
    after a stop signal the client's connection may then close in its background thread and log
    a traceback at INFO after the one line that says what happened. The batch reports every
    failed task by name, so nothing Dask logs here is needed."""
    import logging

    for handler in logging.getLogger("distributed").handlers:
        if isinstance(handler, logging.StreamHandler):
            handler.setLevel(logging.CRITICAL)


def run_on_dask(jobs: Sequence[Job], workers: int | None, scheduler: str | None,
                on_done: Callable[[Outcome], None], connect_timeout: float = CONNECT_TIMEOUT) -> str:
    """Run ``jobs`` as Dask tasks, calling ``on_done`` with each outcome as it finishes; returns
    where they ran (for the summary). :class:`InputError` when the scheduler cannot be reached;
    a stop signal closes the cluster and raises :class:`~magcal_ros.errors.Stopped`."""
    from distributed import as_completed

    from magcal_ros.app.batch_task import run_job

    import logging

    # A stop while workers start leaves Dask's start-up tasks failed and never awaited: asyncio would log
    # each with its traceback at exit, after the one line that says what happened.
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    _quiet_dask_logs()
    cluster: Any = None
    with StopSignals() as stop:
        try:
            if scheduler:
                client, count = connect_scheduler(scheduler, connect_timeout, stop)
                where = f"the Dask cluster at {scheduler} ({count} worker{'s' if count != 1 else ''})"
                if not count:
                    print(f"  note: the Dask cluster at {scheduler} has no worker yet: the tasks wait for one "
                          "(Ctrl-C stops the batch)", file=sys.stderr, flush=True)
            else:
                n = workers or default_workers()
                cluster, client = _local_cluster(n, stop)
                where = f"{n} local worker process{'es' if n != 1 else ''}"
            with client:
                stop.check()
                tag = uuid.uuid4().hex[:8]
                keys = [f"magcal-batch-{tag}-{i}-{job.name}" for i, job in enumerate(jobs)]
                futures = client.map(run_job, list(jobs), key=keys, pure=False, retries=0)
                by_key = dict(zip(keys, jobs))
                done = as_completed(futures)
                while not done.is_empty():
                    stop.check()
                    finished = done.next_batch(block=False)
                    if not finished:
                        time.sleep(0.1)
                    for fut in finished:
                        job = by_key[fut.key]
                        if fut.status == "finished":
                            outcome = fut.result()
                        else:
                            try:
                                exc = fut.exception()
                            except BaseException as cancelled:  # a cancelled future raises instead
                                exc = cancelled
                            outcome = job.outcome("failed", reason=failure_reason(exc))
                        fut.release()
                        on_done(outcome)
                        stop.check()
        finally:
            if cluster is not None:
                cluster.close()
    return where


def _clean_unfinished(jobs: Sequence[Job]) -> None:
    """Remove what stopped tasks left beside their outputs (their worker processes are gone;
    a task still running elsewhere keeps its partial output, which its next run cleans up)."""
    from magcal_ros.io.atomic import recover

    for job in jobs:
        for target in (job.output, job.calibration_out):
            if target:
                recover(target)


def prepare_output(outdir: Path) -> list[Path]:
    """Check, before anything runs, that OUTDIR takes the batch's files: create it and its records folder
    when missing and write (then remove) a file in each. Returns the directories it created, outermost
    first; :class:`InputError` naming the cause (a read-only directory ran every task before failing)."""
    import tempfile

    from magcal_ros.app.campaign import RECORDS_DIR

    created: list[Path] = []
    for folder in (outdir, outdir / RECORDS_DIR):
        try:
            missing = [d for d in (folder, *folder.parents) if not d.exists()]
            folder.mkdir(parents=True, exist_ok=True)
            created += reversed(missing)
            fd, probe = tempfile.mkstemp(prefix=".magcal_batch_probe_", dir=folder)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            remove_empty(created)
            where = exc.filename if exc.filename and Path(exc.filename) in (folder, *folder.parents) else folder
            raise InputError(f"output directory {outdir} cannot be written ({where}: {exc.strerror or exc}); "
                             "nothing run") from None
    return created


def remove_empty(created: Sequence[Path]) -> None:
    """Remove the directories :func:`prepare_output` created that are still empty (innermost first)."""
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()


def _triage(jobs: Sequence[Job], force: bool) -> tuple[dict[str, Outcome], list[Job]]:
    """Outcomes known before anything runs (failed at once; done earlier and unchanged: skipped, unless
    ``force``) and the jobs left to run."""
    from magcal_ros.app.campaign import digest, finished

    outcomes: dict[str, Outcome] = {}
    pending = []
    digests: dict[str, str] = {}
    for job in jobs:
        if job.problem:
            outcomes[job.name] = job.outcome("failed", reason=job.problem)
            continue
        if not force:
            key = digests.setdefault(job.calibration, digest(job.calibration) if job.calibration else "")
            earlier = finished(job, key)
            if earlier is not None:
                outcomes[job.name] = replace(earlier, status="skipped", reason="")
                continue
        pending.append(job)
    return outcomes, pending


def _announce(console: Console, outcomes: dict[str, Outcome], others: Sequence[Outcome]) -> None:
    """The failures known before the run, the recordings skipped as done and the files that are none."""
    for o in outcomes.values():
        if o.status == "failed":
            console.done(o)
    skipped = sum(o.status == "skipped" for o in outcomes.values())
    if skipped:
        console.line(f"  {skipped} recording{'s' if skipped != 1 else ''} already done, unchanged: skipped "
                     "(--force redoes them)")
    if others:
        names = ", ".join(o.name for o in others[:5]) + (f" and {len(others) - 5} more" if len(others) > 5 else "")
        console.line(f"  note: {len(others)} file{'s' if len(others) != 1 else ''} found that "
                     f"{'are' if len(others) != 1 else 'is'} not a recording, skipped (listed in the report): {names}",
                     error=True)


def _report(outdir: Path, ordered: list[Outcome], others: Sequence[Outcome]) -> list[Outcome]:
    """Write OUTDIR's report: this run's recordings, the files it skipped as none, and every output an
    earlier run (of any inputs) wrote there that is still as written. Returns the earlier ones."""
    from magcal_ros.app import batch_report, campaign

    mine = {o.name for o in ordered}
    earlier = [replace(o, status="skipped", reason="") for name, o in campaign.recorded_outcomes(outdir).items()
               if name not in mine]
    rows = ordered + earlier + list(others)
    batch_report.write_csv(outdir / campaign.REPORT_CSV, rows)
    batch_report.write_html(outdir / campaign.REPORT_HTML, rows, str(outdir))
    return earlier


def _names(items: Sequence[Outcome]) -> str:
    """Up to five names, and how many more."""
    return ", ".join(o.name for o in items[:5]) + (f" and {len(items) - 5} more" if len(items) > 5 else "")


def _summary_line(ordered: Sequence[Outcome], skipped: int) -> str:
    """``batch: N recordings: C corrected, K skipped, F failed (NAMES)[, G flagged (NAMES)]``."""
    from magcal_ros.app.batch_report import flag_of

    failed = [o for o in ordered if o.status == "failed"]
    flagged = [o for o in ordered if flag_of(o)]
    corrected = sum(o.status == "corrected" for o in ordered)
    return (f"batch: {len(ordered)} recording{'s' if len(ordered) != 1 else ''}: {corrected} corrected, {skipped} "
            f"skipped, {len(failed)} failed"
            + (f" ({_names(failed)})" if failed else "")
            + (f", {len(flagged)} flagged far above the noise floor ({_names(flagged)})" if flagged else ""))


def cmd_batch(args: argparse.Namespace) -> int:
    """Plan, check OUTDIR, skip what is done, run the rest on Dask, write the report; exit 1 if any
    recording failed."""
    from magcal_ros.app import campaign
    from magcal_ros.app.progress import ProgressBar

    t0 = time.perf_counter()
    jobs, notes, others = plan(args)
    for note in notes:
        print(f"  note: {note}", file=sys.stderr)
    outdir = Path(args.output).absolute()
    created = prepare_output(outdir)
    outcomes, pending = _triage(jobs, args.force)
    skipped = sum(o.status == "skipped" for o in outcomes.values())
    bar = ProgressBar(len(pending), "batch", unit="rec", enabled=False if args.quiet else None)
    console = Console(bar, args.quiet)
    _announce(console, outcomes, others)
    where = "nothing to run"
    if pending:
        def on_done(o: Outcome) -> None:
            outcomes[o.name] = o
            console.done(o)
            bar(1)

        try:
            with bar:
                where = run_on_dask(pending, args.workers, args.scheduler, on_done,
                                    args.connect_timeout or CONNECT_TIMEOUT)
        except MagcalError:
            remove_empty(created)  # refused before any task ran (a scheduler that is none)
            raise
        except KeyboardInterrupt:
            _clean_unfinished([j for j in pending if j.name not in outcomes])
            remove_empty(created)  # stopped before any task wrote: nothing left behind
            raise
    ordered = [outcomes[j.name] for j in jobs]
    earlier = _report(outdir, ordered, others)
    print(_summary_line(ordered, skipped) + f"; {time.perf_counter() - t0:.1f} s on {where}")
    more = f" (with {len(earlier)} more recording{'s' if len(earlier) != 1 else ''} earlier runs wrote there)" \
        if earlier else ""
    print(f"  report {outdir / campaign.REPORT_HTML} and {outdir / campaign.REPORT_CSV}{more}")
    return 1 if any(o.status == "failed" for o in ordered) else 0
