"""Running trials in-process, on local processes, or on dask.distributed; saving and resuming.

Backends
--------
* in-process (default);
* ``workers=N``: a :class:`concurrent.futures.ProcessPoolExecutor` with
  ``N`` spawned processes;
* ``dask_workers=N``: a ``distributed.LocalCluster(n_workers=N,
  threads_per_worker=1, processes=True, dashboard_address=None)``;
  ``scheduler="tcp://host:port"``: an existing dask scheduler (its workers
  must be able to import bayescal).  A trial whose worker died is
  rescheduled by the dask scheduler (``distributed.scheduler.allowed-failures``,
  default 3); tasks are also submitted with ``retries=``, which reruns a
  trial that raised an exception.

Every trial is seeded by its index (:func:`bayescal.compare.trial.trial_rng`),
so the records are identical whatever the backend and the number of workers.

Resume: with ``out``, each finished trial is appended to ``out/trials.jsonl``
as one JSON line (write, flush, fsync), and ``out/config.json`` holds the
configuration.  A rerun with the same ``out`` and configuration reads the
finished trials and runs only the missing ones; a torn last line (a run
killed mid-write) is discarded.  A different configuration in the same
``out`` is an error, never a silent mix.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Iterator

from ..errors import InputError
from ..io import write_json_atomic
from ..progress import report, reporting
from ..io.answers import to_jsonable
from .trial import METRICS, CompareConfig, run_trial

__all__ = ["run_trials", "load_trials", "TRIALS_FILE", "CONFIG_FILE"]

TRIALS_FILE = "trials.jsonl"
CONFIG_FILE = "config.json"


def _normalise(record: dict) -> dict:
    # the JSON round trip makes in-memory and resumed records bit-identical (repr of floats is exact)
    return json.loads(json.dumps(to_jsonable(record)))


def load_trials(out: str | os.PathLike, config: CompareConfig) -> dict[int, dict]:
    """Finished trials saved in ``out`` for this configuration (empty if none).

    Raises
    ------
    InputError
        If ``out`` holds a different configuration, or a damaged state: a
        ``config.json`` that is not a JSON object, a line of ``trials.jsonl``
        (other than a torn last line, which is dropped) that is not a trial
        record of this configuration (:func:`_check_record`), naming the line.
    """
    from ..io.safe_paths import MAX_JSON_STATE_BYTES, check_replaceable, read_input_text

    out = Path(out)
    cfg_path = out / CONFIG_FILE
    remedy = "remove the folder or choose another --out"
    for state in (cfg_path, out / TRIALS_FILE):
        check_replaceable(state)  # rewritten or appended to: a regular file, not a link, a pipe or a device
    if cfg_path.exists():
        # protect=False: the run rewrites its own state
        text = read_input_text(cfg_path, "a comparison's configuration (JSON)", limit=MAX_JSON_STATE_BYTES,
                               protect=False)
        try:
            saved = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise InputError(f"{cfg_path}: not valid JSON ({exc}); {remedy}") from None
        if not isinstance(saved, dict):
            raise InputError(f"{cfg_path}: expected a JSON object (the comparison's configuration), got "
                             f"{type(saved).__name__}; {remedy}")
        mine = _normalise(config.to_dict())
        diff = sorted(k for k in set(saved) | set(mine) if k != "trials" and saved.get(k) != mine.get(k))
        if diff:
            raise InputError(
                f"{cfg_path}: this folder holds a comparison with a different configuration ({', '.join(diff)} "
                f"differ); choose another --out or remove it"
            )
    path = out / TRIALS_FILE
    done: dict[int, dict] = {}
    if not path.exists():
        return done
    raw = read_input_text(path, "a comparison's saved trials (JSON lines)", limit=MAX_JSON_STATE_BYTES,
                          protect=False).encode("utf-8")
    end = raw.rfind(b"\n") + 1
    if end < len(raw):
        # a torn last line from an interrupted write: drop it so appends start on a fresh line
        with open(path, "r+b") as fh:
            fh.truncate(end)
            fh.flush()
            os.fsync(fh.fileno())
    labels = [s.label for s in config.specs]
    for n, line in enumerate(raw[:end].decode("utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        rec = _check_record(line, labels, f"{path}: line {n}", remedy)
        t = rec["trial"]
        if 0 <= t < config.trials:
            done[t] = rec
    return done


def _number_or_null(v) -> bool:
    """A metric as records hold it: a number, or null for NaN (to_jsonable)."""
    return v is None or (not isinstance(v, bool) and isinstance(v, (int, float)))


def _check_record(line: str, labels: list[str], where: str, remedy: str) -> dict:
    """One saved trial: ``{"trial": int, "nominal": {...}, "methods": {label: {"success": bool, ...}}}``."""
    try:
        rec = json.loads(line)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{where}: not a JSON trial record ({exc}); {remedy}") from None
    if not isinstance(rec, dict):
        raise InputError(f"{where}: expected a JSON object (a trial record); {remedy}")
    t = rec.get("trial")
    if isinstance(t, bool) or not isinstance(t, int) or t < 0:
        raise InputError(f"{where}: expected \"trial\": a non-negative integer, got {t!r}; {remedy}")
    methods = rec.get("methods")
    if not isinstance(rec.get("nominal"), dict) or not isinstance(methods, dict):
        raise InputError(f"{where}: expected \"nominal\" and \"methods\" objects; {remedy}")
    if not all(_number_or_null(v) for v in rec["nominal"].values()):
        raise InputError(f"{where}: \"nominal\" holds a value that is not a number; {remedy}")
    for label in labels:
        entry = methods.get(label)
        if not isinstance(entry, dict) or not isinstance(entry.get("success"), bool):
            raise InputError(f"{where}: no result of method {label!r} (an object with \"success\"); {remedy}")
        if not isinstance(entry.get("message", ""), str) or (not entry["success"] and "message" not in entry):
            raise InputError(f"{where}: method {label!r}: expected a \"message\" text; {remedy}")
        bad = [k for k, v in entry.items() if k in METRICS + ("seconds",) and not _number_or_null(v)]
        if bad:
            raise InputError(f"{where}: method {label!r}: {bad[0]} is not a number; {remedy}")
    return rec


def _append(path: Path, record: dict) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def _in_process(cfg: dict, todo: list[int]) -> Iterator[dict]:
    for t in todo:
        yield run_trial(cfg, t)


def _processes(cfg: dict, todo: list[int], workers: int) -> Iterator[dict]:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as ex:
        futs = [ex.submit(run_trial, cfg, t) for t in todo]
        for f in as_completed(futs):
            yield f.result()


def _dask(cfg: dict, todo: list[int], *, dask_workers: int, scheduler: str | None, retries: int) -> Iterator[dict]:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as exc:  # pragma: no cover - dask is a declared dependency of the extra
        raise InputError("dask.distributed is not installed: pip install 'bayescal[dask]'") from exc
    import logging

    # shutting a LocalCluster down logs harmless heartbeat errors (LIBRARIES.md); keep stderr for progress
    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    if scheduler:
        cluster = None
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise InputError(f"--scheduler: cannot reach a dask scheduler at {scheduler} ({exc})") from exc
    else:
        with warnings.catch_warnings():
            # with no dashboard the scheduler still serves /health on a default port, and warns when
            # another cluster on this host holds it; it then takes a free port, which is all we need
            warnings.filterwarnings("ignore", message="Port .* is already in use", category=UserWarning)
            cluster = LocalCluster(n_workers=dask_workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        client = Client(cluster)
    try:
        futs = [client.submit(run_trial, cfg, t, retries=retries, pure=False) for t in todo]
        for f in as_completed(futs):
            yield f.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _collect(it, done: dict, path: Path | None, bar, trials: int) -> None:
    """Each finished trial into ``done`` (and appended to ``path``), the bar or a progress line moved on."""
    drawn = bar is not None and not bar.disable
    # a bar drawn on the terminal says how far the trials are: the fits' own progress lines would break it
    with reporting(None) if drawn else contextlib.nullcontext():
        for rec in it:
            rec = _normalise(rec)
            done[int(rec["trial"])] = rec
            if path is not None:
                _append(path, rec)
            if bar is not None:
                bar.update(1)
            report(lambda: f"{len(done)} of {trials} trials done")


def run_trials(
    config: CompareConfig,
    *,
    out: str | os.PathLike | None = None,
    workers: int = 0,
    dask_workers: int = 0,
    scheduler: str | None = None,
    retries: int = 3,
    progress: bool = True,
) -> tuple[list[dict], dict]:
    """Run (or resume) every trial of a comparison.

    Parameters
    ----------
    config : CompareConfig
    out : path, optional
        Folder for ``config.json`` and ``trials.jsonl`` (resume).
    workers : int
        Local processes (0 or 1: in-process).
    dask_workers : int
        Workers of a dask LocalCluster (0: no dask).
    scheduler : str, optional
        Address of a running dask scheduler (``tcp://host:port``).
    retries : int
        dask retries per task of a trial that raised (a dead worker's trials are
        rescheduled by dask itself, up to ``distributed.scheduler.allowed-failures``).
    progress : bool
        tqdm progress bar on stderr.

    Returns
    -------
    records : list of dict
        One per trial, sorted by trial index.
    info : dict
        ``backend``, ``resumed`` (trials read from ``out``), ``ran``, ``seconds``.
    """
    if workers < 0 or dask_workers < 0:
        raise InputError("workers: expected a number >= 0")
    if scheduler and dask_workers:
        raise InputError("give either --scheduler (an existing dask cluster) or --dask-workers (a local one), not both")
    config.specs  # validate the method names before starting anything
    cfg = config.to_dict()
    done: dict[int, dict] = {}
    path = None
    if out is not None:
        out = Path(out)
        done = load_trials(out, config)
        from ..io.safe_paths import output_folder

        output_folder(out)  # not through a link (bayescal.io.safe_paths)
        write_json_atomic(out / CONFIG_FILE, cfg)
        path = out / TRIALS_FILE
    todo = [t for t in range(config.trials) if t not in done]
    if scheduler or dask_workers:
        backend = f"dask ({scheduler})" if scheduler else f"dask LocalCluster ({dask_workers} workers)"
        it = _dask(cfg, todo, dask_workers=dask_workers, scheduler=scheduler, retries=retries)
    elif workers > 1:
        backend = f"local processes ({workers})"
        it = _processes(cfg, todo, workers)
    else:
        backend = "in-process"
        it = _in_process(cfg, todo)
    t0 = time.perf_counter()
    bar = None
    if progress and todo:
        from tqdm import tqdm

        # disable=None: no bar when stderr is not a terminal (a log file gets no carriage-return lines)
        bar = tqdm(total=config.trials, initial=len(done), desc="trials", unit="trial", file=sys.stderr, disable=None)
    try:
        _collect(it if todo else (), done, path, bar, config.trials)
    finally:
        if bar is not None:
            bar.close()
    records = [done[t] for t in range(config.trials)]
    return records, {"backend": backend, "resumed": config.trials - len(todo), "ran": len(todo),
                     "seconds": time.perf_counter() - t0}
