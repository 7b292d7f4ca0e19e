"""A campaign for ``magcal batch``: which recordings, which calibration each, what is already done.

- **Recordings**: rosbag2 directories (a directory is a bag only by its ``metadata.yaml``)
  and ``.csv`` files. An input that is neither is a directory to walk: every bag and CSV
  below it, hidden entries and the output directory left out, named by its path relative
  to the walked directory (kept under OUTDIR); every other file found there (notes, a
  stray ``.db3`` without its ``metadata.yaml``) is listed as skipped, never run. A
  recording given directly, or in a list file (``@FILE``/``--list FILE``: one path per
  line, ``#`` comments, paths relative to the list file), is named by its last component.
- **Vehicle**: the name of the directory holding the recording, or with a pattern the
  group ``vehicle`` (else group 1, else the whole match) of its first match in the
  recording's absolute path; no match: no vehicle.
- **Calibration**: one calibration file for all, or a mapping file, a YAML document with a
  top-level ``magcal_batch`` block::

      magcal_batch:
        calibrations:                     # first entry that matches wins
          - {vehicle: auv1, calibration: auv1.yaml}
          - {match: "glider*/2025-*", calibration: glider_2025.yaml}
          - {calibration: default.yaml}   # no condition: every recording

  ``vehicle`` is a glob over the vehicle name, ``match`` a glob over the recording's name
  (its path under OUTDIR) or its absolute path (``*`` also crosses ``/``); an entry with
  both needs both. Calibration paths are relative to the mapping file.
- **Done**: after a recording's outputs are complete, a small JSON record is written
  atomically under ``OUTDIR/.magcal_batch/`` with the size and modification time of every
  input and output file, the calibration's SHA-256 and the options. A later run skips the
  recording while all of these are unchanged (``--force`` redoes it). The records are also
  what the report of OUTDIR lists: every output a run of any inputs wrote there and that is
  still as it was written (:func:`recorded_outcomes`).
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from magcal_ros.errors import InputError

RECORDS_DIR = ".magcal_batch"
"""Completion records under OUTDIR (one JSON file per recording, named like its output)."""
REPORT_CSV = "report.csv"
REPORT_HTML = "report.html"
MAPPING_KEY = "magcal_batch"
RECORD_FORMAT = 1
STORAGE_SUFFIXES = (".db3", ".mcap")


# --------------------------------------------------------------------------- what was done


@dataclass(frozen=True)
class Outcome:
    """One recording's result: what ``magcal correct`` wrote and what its output shows.

    Times are integer nanoseconds (set stamps), fields in T, gradients in T/m. ``None``:
    not known (a failed recording; no reference intensity or noise in the calibration).
    """

    name: str
    vehicle: str
    status: str
    """``corrected`` (this run), ``skipped`` (done by an earlier run, unchanged) or ``failed``."""
    input: str
    output: str = ""
    calibration: str = ""
    reason: str = ""
    sets: int | None = None
    drops: int | None = None
    """Input samples that gave no corrected set (incomplete, repeated, NaN, no fresh current, ...)."""
    start_ns: int | None = None
    end_ns: int | None = None
    intensity: float | None = None
    """The reference intensity F the TMI residual is taken against (T)."""
    noise: float | None = None
    """The calibration's noise per axis (T): the RMS over sensors of its provenance ``noise``."""
    tmi_median: float | None = None
    """Median of ``| |B| - F |`` over every corrected vector (T)."""
    tmi_p95: float | None = None
    """95th percentile of the same (T)."""
    tensor_noise: float | None = None
    """Set-to-set noise of the measured gradient components (T/m), see StepNoise."""
    seconds: float | None = None
    """Wall time of its task (s)."""
    worker: str = ""
    """Where its task ran: ``host:pid`` of the worker process."""
    notes: tuple[str, ...] = ()
    other: bool = False
    """A file found among the recordings that is none (``status`` skipped, ``reason`` why): listed, never run."""

    def ratio(self, value: float | None) -> float | None:
        """``value`` in units of the calibration's noise (None when either is unknown)."""
        return None if value is None or not self.noise else value / self.noise

    def as_json(self) -> dict[str, Any]:
        """A JSON-able dict (:meth:`from_json` reads it back)."""
        d = asdict(self)
        d["notes"] = list(self.notes)
        return d

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "Outcome":
        """The outcome of :meth:`as_json` (unknown keys ignored)."""
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in data.items() if k in names}
        kw["notes"] = tuple(kw.get("notes") or ())
        return cls(**kw)


@dataclass(frozen=True)
class Job:
    """One recording of a batch: everything a worker needs, as absolute paths."""

    name: str
    """Path of its output under OUTDIR ('/'-separated)."""
    input: str
    output: str
    vehicle: str
    calibration: str
    """The calibration file to correct with (with ``calibrate_args``: the prior, may be empty)."""
    record: str
    correct_args: tuple[str, ...] = ()
    """Options for ``magcal correct`` (besides input, -c, -o)."""
    calibrate_args: tuple[str, ...] | None = None
    """Options for ``magcal calibrate`` (besides input, -o, --prior); None: correct only."""
    calibration_out: str = ""
    """Where ``--calibrate`` writes this recording's own calibration."""
    reference_field: float | None = None
    uncorrected: tuple[str, ...] = ()
    problem: str = ""
    """Why it cannot run at all (no calibration matches it, the input is missing)."""

    @property
    def used_calibration(self) -> str:
        """The calibration the output is corrected with."""
        return self.calibration_out if self.calibrate_args is not None else self.calibration

    def outcome(self, status: str, **values: Any) -> Outcome:
        """An :class:`Outcome` of this job."""
        return Outcome(self.name, self.vehicle, status, self.input, self.output, self.used_calibration, **values)


# --------------------------------------------------------------------------- finding recordings


def is_bag_dir(path: Path) -> bool:
    """A rosbag2 directory: one that holds a ``metadata.yaml`` (a broken bag counts). Storage files alone
    do not make one: a campaign folder with a stray ``.db3`` is still a folder of recordings."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def not_a_recording(path: Path) -> str:
    """Why a file found in a walk is not a recording (one line)."""
    if path.suffix in STORAGE_SUFFIXES:
        return ("not a recording: a rosbag2 storage file without the bag's metadata.yaml beside it "
                "('ros2 bag reindex' on its folder writes one)")
    return "not a recording: neither a .csv file nor a rosbag2 directory"


def is_csv_path(path: Path) -> bool:
    """A CSV recording by name (``.csv``)."""
    return path.name.lower().endswith(".csv")


def read_list(path: Path) -> list[Path]:
    """Paths in a list file: one per line, blank lines and ``#`` comments skipped, relative to the file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"cannot read list file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"list file {path} is not text") from None
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            p = Path(os.path.expanduser(line))
            out.append(p if p.is_absolute() else path.parent / p)
    return out


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def walk(root: Path, skip: Path) -> tuple[list[tuple[str, Path]], list[tuple[str, Path]]]:
    """Every recording under ``root`` and every other file: ``(name relative to root, path)``, each
    sorted; ``skip`` (OUTDIR) and hidden entries left out, bag directories not entered."""
    found: list[tuple[str, Path]] = []
    others: list[tuple[str, Path]] = []
    for here, dirs, files in os.walk(root, followlinks=True):
        here_p = Path(here)
        keep = []
        for d in sorted(dirs):
            p = here_p / d
            if d.startswith(".") or _inside(p.resolve(), skip):
                continue
            if is_bag_dir(p):
                found.append((p.relative_to(root).as_posix(), p))
            else:
                keep.append(d)
        dirs[:] = keep
        for f in sorted(files):
            p = here_p / f
            if not f.startswith(".") and not _inside(p.resolve(), skip):
                (found if is_csv_path(p) else others).append((p.relative_to(root).as_posix(), p))
    return sorted(found), sorted(others)


@dataclass(frozen=True)
class Found:
    """What the command line names: recordings ``(name, path)`` in order, the other files its walks met
    (listed as skipped) and notes."""

    recordings: list[tuple[str, Path]]
    others: list[tuple[str, Path]]
    notes: list[str]


def _paths(inputs: Sequence[str], list_files: Sequence[str]) -> list[Path]:
    """The paths the inputs name: ``@FILE`` among ``inputs`` and each of ``list_files`` read as list files."""
    paths: list[Path] = []
    for token in inputs:
        paths += read_list(Path(token[1:])) if token.startswith("@") and len(token) > 1 else [Path(token)]
    for lf in list_files:
        paths += read_list(Path(lf))
    return paths


def find_recordings(inputs: Sequence[str], list_files: Sequence[str], outdir: Path) -> Found:
    """Recordings named by the command line (see :class:`Found`).

    A path that does not exist is kept (its task fails, naming it); a directory that holds no
    recording is a note; the files of walked directories that are not recordings are kept apart.
    """
    found = Found([], [], [])
    for p in _paths(inputs, list_files):
        if p.is_dir() and not is_bag_dir(p):
            if _inside(p.resolve(), outdir):
                raise InputError(f"{p} is inside the output directory {outdir}: give the recordings' directory as input")
            recordings, others = walk(p, outdir)
            if not recordings:
                found.notes.append(f"{p}: no recordings (rosbag2 directories or .csv files) found")
            found.recordings.extend(recordings)
            found.others.extend(others)
        else:
            found.recordings.append((p.name or str(p), p))
    return found


def vehicle_of(path: Path, pattern: re.Pattern[str] | None) -> str:
    """The vehicle a recording belongs to (see the module docstring); '' when the pattern does not match."""
    if pattern is None:
        return path.absolute().parent.name
    m = pattern.search(path.absolute().as_posix())
    if m is None:
        return ""
    if "vehicle" in pattern.groupindex:
        return m.group("vehicle") or ""
    return (m.group(1) if pattern.groups else m.group(0)) or ""


def vehicle_pattern(text: str | None) -> re.Pattern[str] | None:
    """``--vehicle-pattern``, compiled; :class:`InputError` for a bad expression."""
    if not text:
        return None
    try:
        return re.compile(text)
    except re.error as exc:
        raise InputError(f"--vehicle-pattern {text!r} is not a regular expression: {exc}") from None


# --------------------------------------------------------------------------- calibrations


@dataclass(frozen=True)
class Rule:
    """One entry of a calibration mapping."""

    calibration: Path
    vehicle: str | None = None
    match: str | None = None

    def applies(self, name: str, path: Path, vehicle: str) -> bool:
        """Whether this entry covers the recording ``name`` at ``path`` of ``vehicle``."""
        if self.vehicle is not None and not fnmatch.fnmatchcase(vehicle, self.vehicle):
            return False
        if self.match is not None and not (fnmatch.fnmatchcase(name, self.match)
                                           or fnmatch.fnmatchcase(path.absolute().as_posix(), self.match)):
            return False
        return True


@dataclass(frozen=True)
class CalibrationMap:
    """Calibrations by recording: one file for all, or the rules of a mapping file."""

    source: Path
    rules: tuple[Rule, ...] = field(default=())
    mapping: bool = False

    def lookup(self, name: str, path: Path, vehicle: str) -> Path | None:
        """The calibration of a recording, or None when no entry covers it."""
        return next((r.calibration for r in self.rules if r.applies(name, path, vehicle)), None)

    def missing(self, name: str, vehicle: str) -> str:
        """Why a recording has no calibration (one line)."""
        who = f"vehicle {vehicle}" if vehicle else "no vehicle"
        return f"no entry of {self.source} covers {name} ({who})"


def _mapping_of(text: str) -> Any:
    """The ``magcal_batch`` block of a YAML text, or None when it is not a mapping file."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError:
        return None  # not YAML at all: read as a calibration file, which names the error
    return doc.get(MAPPING_KEY) if isinstance(doc, dict) and MAPPING_KEY in doc else None


def load_calibrations(path: str | os.PathLike[str]) -> CalibrationMap:
    """``-c FILE``: a calibration file (used for every recording) or a mapping file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read calibration file {p}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"calibration file {p} is not text") from None
    block = _mapping_of(text)
    if block is None:
        return CalibrationMap(p, (Rule(p),))
    entries = block.get("calibrations") if isinstance(block, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{p}: {MAPPING_KEY} needs 'calibrations:', a list of {{vehicle|match, calibration}} entries")
    rules = []
    for i, e in enumerate(entries, start=1):
        if not isinstance(e, dict) or not isinstance(e.get("calibration"), str) or not e["calibration"].strip():
            raise InputError(f"{p}: calibrations entry {i} needs 'calibration: FILE'")
        unknown = sorted(set(e) - {"vehicle", "match", "calibration"})
        if unknown:
            raise InputError(f"{p}: calibrations entry {i}: unknown key {', '.join(unknown)} "
                             "(keys: vehicle, match, calibration)")
        for key in ("vehicle", "match"):
            if key in e and not isinstance(e[key], (str, int)):
                raise InputError(f"{p}: calibrations entry {i}: {key} must be a text glob")
        cal = Path(os.path.expanduser(e["calibration"]))
        rules.append(Rule(cal if cal.is_absolute() else p.parent / cal,
                          None if e.get("vehicle") is None else str(e["vehicle"]),
                          None if e.get("match") is None else str(e["match"])))
    return CalibrationMap(p, tuple(rules), mapping=True)


# --------------------------------------------------------------------------- completion records


def signature(path: str | os.PathLike[str]) -> list[list[Any]]:
    """``[relative name, size, mtime ns]`` of a file, or of every file in a directory (recursively)."""
    p = Path(path)
    try:
        if p.is_dir():
            files = sorted(f for f in p.rglob("*") if f.is_file())
            return [[f.relative_to(p).as_posix(), (s := f.stat()).st_size, s.st_mtime_ns] for f in files]
        s = p.stat()
    except OSError:
        return []
    return [[p.name, s.st_size, s.st_mtime_ns]]


def digest(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes ('' when it cannot be read)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError:
        return ""
    return h.hexdigest()


def record_key(job: Job, calibration_digest: str) -> dict[str, Any]:
    """What a record must match besides the files: the options and the calibration's content."""
    return {
        "format": RECORD_FORMAT,
        "input_path": job.input,
        "output_path": job.output,
        "calibration_path": job.calibration,
        "calibration_sha256": calibration_digest,
        "correct_args": list(job.correct_args),
        "calibrate_args": None if job.calibrate_args is None else list(job.calibrate_args),
        "reference_field": job.reference_field,
        "uncorrected": list(job.uncorrected),
    }


def files_state(job: Job) -> dict[str, Any]:
    """Signatures of the input, the output and (``--calibrate``) the recording's own calibration."""
    state = {"input": signature(job.input), "output": signature(job.output)}
    if job.calibrate_args is not None:
        state["calibration_out"] = signature(job.calibration_out)
    return state


def write_record(job: Job, calibration_digest: str, outcome: Outcome) -> None:
    """Write the completion record of ``job`` atomically (after its outputs are complete; io/atomic)."""
    from magcal_ros.io.atomic import atomic_path

    path = Path(job.record)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {**record_key(job, calibration_digest), "files": files_state(job), "outcome": outcome.as_json()}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1), encoding="utf-8")


def finished(job: Job, calibration_digest: str) -> Outcome | None:
    """The recorded outcome when ``job``'s outputs are complete and current, else None.

    Complete and current: the record exists and parses, its options and calibration
    content are the job's, every input and output file has the size and modification time
    recorded when the run finished, and the output is not older than the input.
    """
    try:
        data = json.loads(Path(job.record).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or any(data.get(k) != v for k, v in record_key(job, calibration_digest).items()):
        return None
    state = files_state(job)
    if not state["output"] or not state["input"] or data.get("files") != state:
        return None
    newest_input = max(s[2] for s in state["input"])
    if min(s[2] for s in state["output"]) < newest_input:
        return None
    try:
        return Outcome.from_json(data["outcome"])
    except (KeyError, TypeError):
        return None


def _recorded(outdir: Path, path: Path) -> Outcome | None:
    """The outcome a record at ``path`` holds while its output is there as it was written, else None."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        name = path.relative_to(outdir / RECORDS_DIR).as_posix()[: -len(".json")]
        output = Path(data["output_path"])
        if output.resolve() != (outdir / name).resolve() or data["files"]["output"] != (now := signature(output)) \
                or not now:
            return None
        outcome = Outcome.from_json(data["outcome"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return outcome if outcome.status == "corrected" and outcome.name == name else None


def recorded_outcomes(outdir: str | os.PathLike[str]) -> dict[str, Outcome]:
    """Every recording whose output a run (of any inputs) wrote in ``outdir`` and that is still as
    written: its recorded outcome by name. Records of removed or altered outputs are left out."""
    root = Path(outdir).absolute()
    records = root / RECORDS_DIR
    found: dict[str, Outcome] = {}
    for path in sorted(records.rglob("*.json")):
        hidden = any(part.startswith(".") for part in path.relative_to(records).parts)  # a write in progress
        if not hidden and path.is_file():
            outcome = _recorded(root, path)
            if outcome is not None:
                found[outcome.name] = outcome
    return found


def record_path(outdir: Path, name: str) -> Path:
    """Where the completion record of the output ``name`` lives."""
    return outdir / RECORDS_DIR / (name + ".json")


def reserved(name: str) -> bool:
    """Names under OUTDIR a recording cannot take (the reports, the records)."""
    first = name.split("/", 1)[0]
    return name in (REPORT_CSV, REPORT_HTML) or first == RECORDS_DIR


def duplicates(names: Iterable[tuple[str, Path]]) -> list[str]:
    """One line per output name two different recordings would write."""
    seen: dict[str, Path] = {}
    out = []
    for name, path in names:
        if name in seen and seen[name].resolve() != path.resolve():
            out.append(f"{seen[name]} and {path} would both write {name}")
        seen.setdefault(name, path)
    return out
