"""The distributed engines for FreiPose's long jobs on SLURM: submitit against Dask.

Runs on the SLURM this machine reaches (``.ci/start-slurm`` starts a single-node one) and
measures, for ``submitit`` (what ``freipose.cluster`` uses) and ``dask-jobqueue``'s
``SLURMCluster`` (Dask's ``distributed`` scheduler with its workers as SLURM jobs):

1. **Time to results**: from submission to the results of ``--units`` trivial units
   (``operator.neg``) and of ``--units`` units that sleep ``--sleep`` seconds, with
   ``--parallelism`` one-core jobs (submitit: array tasks) or workers (Dask) at a time. Each
   engine runs ``--repeat`` times, in alternating order, and the medians are kept. A Dask run
   is *cold* (the cluster and its worker jobs started with the submission) and then *warm*
   (the same work again on the running workers). From the sleeping units it derives the
   overhead per unit on a slot, ``(time - waves * sleep) / waves`` with
   ``waves = ceil(units / parallelism)``, and the speed-up over running them one by one.
   submitit's results are read from its result files, polled every 0.2 s.
2. **A cancelled job**: two units that sleep ``--cancel-sleep`` seconds; once the first has
   run for 2 s, its job (submitit: its array task; Dask: the worker job that runs it) is
   cancelled with ``scancel``. The engine's own API is then asked for that unit's result for
   at most ``--cancel-timeout`` seconds: did it rerun the unit (how many times it started,
   read from files the unit writes), report an error (which), or give no answer (the timeout)?
   Also: when ``squeue`` stopped listing the cancelled array task (submitit), whether it
   still lists the cancelled worker job and how many worker jobs are left (Dask). submitit
   is also sent what SLURM sends before a preemption (``SIGTERM``, ``USR2``): it requeues.
3. **What each needs on the cluster**: the TCP ports the submitting process listens on while
   the jobs run (read from ``/proc``), the files the engine writes per unit, and what the
   engine needs running (stated per engine in ``NEEDS``).

Ray is not measured: see ``RAY``. An engine whose packages are missing is skipped, and the
script says what to install: ``pip install "freipose[cluster]"`` (submitit) and
``pip install "freipose[bench]"`` or ``pip install dask distributed dask-jobqueue`` (Dask; to
keep them out of an environment, ``pip install --target DIR ...`` and run the script with
``PYTHONPATH=DIR``).

Usage::

    python benchmarks/engines.py                       # 3 alternated repeats (~5 min)
    python benchmarks/engines.py --repeat 1 --engines submitit
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import math
import operator
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from _results import write_result

ENGINES = ("submitit", "dask")
# engine -> (modules it needs, how to install them)
PACKAGES = {
    "submitit": (("submitit",), 'pip install "freipose[cluster]"'),
    "dask": (
        ("dask", "distributed", "dask_jobqueue"),
        'pip install "freipose[bench]" (or: pip install dask distributed dask-jobqueue; to keep '
        "them out of the environment, pip install --target DIR dask distributed dask-jobqueue "
        "and run with PYTHONPATH=DIR)",
    ),
}
NEEDS = {
    "submitit": {
        "daemons": "none: each unit is a batch job (an array task) that runs a pickled callable",
        "ports": "none between nodes",
        "scheduler_commands": "sbatch, squeue, scancel (sacct where accounting is kept)",
        "shared_file_system": "yes: the pickled callable, its argument, logs and result file",
        "submitting_process": "may exit after sbatch; results are read from files later",
    },
    "dask": {
        "daemons": "a Dask scheduler inside the submitting process for the whole run; each "
        "worker is a SLURM job that holds its allocation until the cluster is closed",
        "ports": "each worker job connects to the scheduler's TCP port on the submitting host "
        "(and workers to each other for data); the dashboard adds one more unless disabled",
        "scheduler_commands": "sbatch, scancel (squeue to scale)",
        "shared_file_system": "no (only for the worker logs); tasks and results travel over TCP",
        "submitting_process": "must stay up until the results are gathered",
    },
}
RAY = (
    "left out: Ray installs from the registry, but on SLURM it runs only as a Ray cluster that "
    "the user starts inside an allocation (`ray start --head` on one node, `ray start "
    "--address=<head>:<port>` on each other node, per Ray's 'Deploying on Slurm' guide), with "
    "the head's GCS port and the object-manager and worker ports open between nodes; it has no "
    "executor that turns a unit into a batch job, so it cannot be measured like the others "
    "without such a head-node setup"
)
POLL_S = 0.2


def missing(engines: Sequence[str] = ENGINES) -> dict[str, str]:
    """Engine -> the message naming its missing packages and how to install them."""
    out = {}
    for engine in engines:
        modules, how = PACKAGES[engine]
        absent = [m for m in modules if importlib.util.find_spec(m) is None]
        if absent:
            out[engine] = f"{engine} skipped: {', '.join(absent)} not installed; {how}"
    return out


def slurm_problem() -> str | None:
    """Why no job can be submitted here (None: ``sinfo`` lists a node that is up)."""
    if shutil.which("sbatch") is None or shutil.which("sinfo") is None:
        return "SLURM is not installed here (sbatch, sinfo); .ci/start-slurm starts one"
    res = subprocess.run(
        ["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=20, check=False
    )
    if res.returncode != 0 or not {"idle", "mixed", "mix", "allocated", "alloc"} & set(
        res.stdout.split()
    ):
        return f"no SLURM node is up (sinfo: {(res.stdout + res.stderr).strip()!r})"
    return None


def listening_ports(pid: int | None = None) -> int:
    """How many TCP sockets process ``pid`` (default: this one) listens on (Linux /proc)."""
    fd_dir = Path(f"/proc/{pid or os.getpid()}/fd")
    inodes = set()
    for fd in fd_dir.iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    count = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()
            if len(cols) > 9 and cols[3] == "0A" and cols[9] in inodes:  # 0A: LISTEN
                count += 1
    return count


def overhead_per_unit(seconds: float, units: int, parallelism: int, work_s: float) -> float:
    """Seconds a slot spends per unit beyond the unit's work: ``(t - waves*work) / waves``."""
    waves = math.ceil(units / parallelism)
    return (seconds - waves * work_s) / waves


def medians(times: dict[str, list[float]]) -> dict[str, float]:
    """The median of each list of repeats."""
    return {k: statistics.median(v) for k, v in times.items() if v}


def marked_nap(arg: tuple[str, str, float]) -> str:
    """A unit that notes each start in ``folder/<name>.<n>`` (with its SLURM job), then sleeps.

    Args:
        arg: (folder, unit name, seconds to sleep).

    Returns:
        The unit's name.
    """
    folder, name, seconds = arg
    job = os.environ.get("SLURM_JOB_ID", "")
    if os.environ.get("SLURM_ARRAY_TASK_ID"):
        job = f"{os.environ['SLURM_ARRAY_JOB_ID']}_{os.environ['SLURM_ARRAY_TASK_ID']}"
    n = len(list(Path(folder).glob(f"{name}.*"))) + 1
    Path(folder, f"{name}.{n}").write_text(job)
    time.sleep(seconds)
    return name


def starts(folder: Path, name: str) -> list[str]:
    """The SLURM jobs of each start of unit ``name``, in order."""
    marks = sorted(folder.glob(f"{name}.*"), key=lambda p: int(p.suffix[1:]))
    return [p.read_text() for p in marks]


def _by_value() -> None:
    """Pickle this module's functions by value, so jobs need not import the script."""
    import cloudpickle

    if __name__ != "__main__":
        cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _until(check: Callable[[], Any], timeout: float, what: str, poll: float = POLL_S) -> Any:
    """Poll ``check`` until it returns something true (TimeoutError after ``timeout`` s)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = check()
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError(f"{what}: nothing after {timeout:.0f} s")


def squeue_lists(job_id: str) -> bool:
    """Whether ``squeue`` still lists job ``job_id`` (an array task as ``<array>_<task>``)."""
    res = subprocess.run(
        ["squeue", "-h", "-r", "-o", "%i"], capture_output=True, text=True, timeout=30, check=False
    )
    return job_id in res.stdout.split()


def scancel(*job_ids: str) -> None:
    """Cancel SLURM jobs (errors ignored: a job may have ended already)."""
    subprocess.run(["scancel", *job_ids], capture_output=True, timeout=30, check=False)


# ---------------------------------------------------------------- submitit
def submitit_executor(folder: Path, args: argparse.Namespace) -> Any:
    """A submitit SLURM executor of one-core, 1 GiB array tasks, ``--parallelism`` at a time."""
    import submitit

    logging.getLogger("submitit").setLevel(logging.ERROR)  # no sacct here: one warning a poll
    ex = submitit.SlurmExecutor(folder=str(folder / "%j"), max_num_timeout=0)
    ex.update_parameters(
        partition=args.partition,
        cpus_per_task=1,
        mem="1024M",
        time=15,
        array_parallelism=args.parallelism,
        job_name="engines",
    )
    return ex


def time_submitit(fn: Callable, items: list, folder: Path, args: argparse.Namespace) -> dict:
    """Seconds from ``map_array`` to all results, the results, and files written per unit."""
    _by_value()
    ex = submitit_executor(folder, args)
    t0 = time.perf_counter()
    jobs = ex.map_array(fn, items)
    ports = listening_ports()
    files = [Path(j.paths.result_pickle) for j in jobs]
    try:
        _until(lambda: all(f.exists() for f in files), args.timeout, "submitit results")
    except TimeoutError:
        scancel(*{j.job_id.split("_")[0] for j in jobs})
        raise
    results = [j.result() for j in jobs]
    seconds = time.perf_counter() - t0
    written = [p for p in folder.rglob("*") if p.is_file()]
    return {
        "seconds": seconds,
        "results": results,
        "listening_ports": ports,
        "files_per_unit": len(written) / len(items),
        "bytes_per_unit": sum(p.stat().st_size for p in written) / len(items),
    }


def cancel_submitit(folder: Path, args: argparse.Namespace) -> dict:
    """Cancel the first of two running units' array task; what ``job.done()/result()`` say."""
    from submitit.core.utils import UncompletedJobError

    _by_value()
    marks = folder / "marks"
    marks.mkdir(parents=True)
    ex = submitit_executor(folder, args)
    jobs = ex.map_array(marked_nap, [(str(marks), f"u{i}", args.cancel_sleep) for i in range(2)])
    try:
        _until(lambda: starts(marks, "u0"), args.timeout, "the first unit's start")
        time.sleep(2)
        scancel(jobs[0].job_id)
        t0 = time.perf_counter()
        out: dict[str, Any] = {"outcome": "no answer", "seconds_to_answer": None}
        gone = None
        while time.perf_counter() - t0 < args.cancel_timeout:
            if gone is None and not squeue_lists(jobs[0].job_id):
                gone = time.perf_counter() - t0
            if jobs[0].done():
                try:
                    jobs[0].result()
                    out["outcome"] = "result"
                except UncompletedJobError as exc:
                    out["outcome"] = "error reported"
                    out["error"] = str(exc).splitlines()[0]
                out["seconds_to_answer"] = time.perf_counter() - t0
                break
            time.sleep(0.5)
        out["squeue_gone_s"] = gone
        out["starts"] = len(starts(marks, "u0"))
        out["other_unit_done"] = _other_done(lambda: jobs[1].result(), args)
        out["sacct_available"] = _sacct_works()
        return out
    finally:
        scancel(jobs[0].job_id.split("_")[0])


def preempt_submitit(folder: Path, args: argparse.Namespace) -> dict:
    """Signal a running unit as SLURM does before a preemption (SIGTERM, then USR2).

    submitit's handler in the job requeues it (``scontrol requeue``); the unit starts again
    once SLURM lets the requeued job begin. Also: the job's state and reason 5 s later.
    """
    _by_value()
    marks = folder / "marks"
    marks.mkdir(parents=True)
    ex = submitit_executor(folder, args)
    ex.update_parameters(array_parallelism=1)
    job = ex.map_array(marked_nap, [(str(marks), "u0", args.cancel_sleep)])[0]
    try:
        _until(lambda: starts(marks, "u0"), args.timeout, "the unit's start")
        time.sleep(2)
        for sig in ("SIGTERM", "USR2"):
            subprocess.run(["scancel", job.job_id, "--signal", sig], timeout=30, check=False)
        t0 = time.perf_counter()
        out: dict[str, Any] = {"outcome": "no answer", "seconds_to_answer": None}
        time.sleep(5)
        listed = subprocess.run(
            ["squeue", "-h", "-j", job.job_id, "-o", "%T (%r)"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        out["state_5s_after"] = listed.stdout.strip()
        try:
            result = Path(job.paths.result_pickle)
            _until(result.exists, args.requeue_timeout, "the result")
            out["outcome"] = "result" if job.result() == "u0" else "wrong result"
            out["seconds_to_answer"] = time.perf_counter() - t0
        except TimeoutError:
            pass
        out["starts"] = len(starts(marks, "u0"))
        return out
    finally:
        scancel(job.job_id.split("_")[0])


def _other_done(result: Callable[[], Any], args: argparse.Namespace) -> bool:
    """Whether the uncancelled unit's result came (waited for at most ``--cancel-sleep`` + 30 s)."""
    import concurrent.futures

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        fut = pool.submit(result)
        try:
            return fut.result(timeout=args.cancel_sleep + 30) == "u1"
        except Exception:  # timeout or the engine's error
            return False


def _sacct_works() -> bool:
    """Whether this SLURM keeps accounting (``sacct`` answers)."""
    res = subprocess.run(
        ["sacct", "-n", "-X"], capture_output=True, text=True, timeout=30, check=False
    )
    return res.returncode == 0


# ---------------------------------------------------------------- dask-jobqueue
def dask_cluster(folder: Path, args: argparse.Namespace) -> tuple[Any, Any]:
    """A SLURMCluster of ``--parallelism`` one-core, 1 GB worker jobs, and its client."""
    from dask_jobqueue import SLURMCluster
    from distributed import Client

    logging.getLogger("distributed").setLevel(logging.ERROR)
    cluster = SLURMCluster(
        queue=args.partition,
        cores=1,
        processes=1,
        memory="1GB",
        walltime="00:15:00",
        python=sys.executable,
        job_name="engines-dask",
        log_directory=str(folder),
        death_timeout=30,
        scheduler_options={"dashboard_address": None},
    )
    client = Client(cluster)
    cluster.scale(jobs=args.parallelism)
    return cluster, client


def time_dask(fn: Callable, items: list, folder: Path, args: argparse.Namespace) -> dict:
    """Cold (cluster started with the submission) and warm seconds to all results."""
    from distributed import wait

    _by_value()
    t0 = time.perf_counter()
    cluster, client = dask_cluster(folder, args)
    try:
        out: dict[str, Any] = {}
        for kind in ("cold", "warm"):
            t = t0 if kind == "cold" else time.perf_counter()
            futures = client.map(fn, items, pure=False)
            wait(futures, timeout=args.timeout)
            out[f"{kind}_results"] = client.gather(futures)
            out[f"{kind}_seconds"] = time.perf_counter() - t
        out["listening_ports"] = listening_ports()
        return out
    finally:
        client.close()
        cluster.close()


def cancel_dask(folder: Path, args: argparse.Namespace) -> dict:
    """Cancel the worker job that runs the first of two units; what its future says."""
    from distributed import wait

    _by_value()
    marks = folder / "marks"
    marks.mkdir(parents=True)
    cluster, client = dask_cluster(folder, args)
    try:
        client.wait_for_workers(args.parallelism, timeout=args.timeout)
        items = [(str(marks), f"u{i}", args.cancel_sleep) for i in range(2)]
        futures = client.map(marked_nap, items, pure=False)
        job = _until(lambda: starts(marks, "u0"), args.timeout, "the first unit's start")[0]
        time.sleep(2)
        scancel(job)
        t0 = time.perf_counter()
        out: dict[str, Any] = {"outcome": "no answer", "seconds_to_answer": None}
        try:
            wait(futures[0], timeout=args.cancel_timeout)
            exc = futures[0].exception()
            if exc is None:
                out["outcome"] = "result"
            else:
                out["outcome"] = "error reported"
                out["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
            out["seconds_to_answer"] = time.perf_counter() - t0
        except TimeoutError:
            pass
        out["job_listed_at_end"] = squeue_lists(job)
        out["starts"] = len(starts(marks, "u0"))
        out["other_unit_done"] = _other_done(lambda: futures[1].result(), args)
        listed = subprocess.run(
            ["squeue", "-h", "-n", "engines-dask", "-o", "%i"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        out["worker_jobs_after"] = len(listed.stdout.split())
        return out
    finally:
        client.close()
        cluster.close()


# ---------------------------------------------------------------- the run
def workloads(args: argparse.Namespace) -> dict[str, tuple[Callable, list, list]]:
    """Name -> (function, arguments, expected results) of the timed units."""
    n = args.units
    return {
        "trivial": (operator.neg, list(range(n)), [-i for i in range(n)]),
        "sleep": (time.sleep, [args.sleep] * n, [None] * n),
    }


def measure_times(engines: Sequence[str], work: Path, args: argparse.Namespace) -> dict:
    """Medians over ``--repeat`` alternated runs of each engine and workload, and its needs."""
    times: dict[str, list[float]] = {}
    extra: dict[str, dict] = {e: {} for e in engines}
    for r in range(args.repeat):
        for engine in engines if r % 2 == 0 else engines[::-1]:
            for name, (fn, items, expected) in workloads(args).items():
                folder = Path(tempfile.mkdtemp(prefix=f"{engine}_{name}_{r}_", dir=work))
                if engine == "submitit":
                    res = time_submitit(fn, items, folder, args)
                    runs = {"": (res["seconds"], res["results"])}
                    extra[engine] |= {
                        k: res[k] for k in ("listening_ports", "files_per_unit", "bytes_per_unit")
                    }
                else:
                    res = time_dask(fn, items, folder, args)
                    runs = {
                        f"_{k}": (res[f"{k}_seconds"], res[f"{k}_results"])
                        for k in ("cold", "warm")
                    }
                    extra[engine]["listening_ports"] = res["listening_ports"]
                for suffix, (seconds, results) in runs.items():
                    if results != expected:
                        raise RuntimeError(f"{engine} {name}: wrong results {results!r}")
                    times.setdefault(f"{engine}{suffix}_{name}_s", []).append(round(seconds, 3))
                    print(f"  {engine}{suffix} {name}: {seconds:.2f} s", file=sys.stderr)
    figures: dict[str, Any] = {"medians": medians(times), "repeats": times}
    serial = args.units * args.sleep
    for key, seconds in figures["medians"].items():
        if key.endswith("_sleep_s"):
            run = key[: -len("_sleep_s")]
            figures[f"{run}_overhead_per_unit_s"] = overhead_per_unit(
                seconds, args.units, args.parallelism, args.sleep
            )
            figures[f"{run}_speedup_vs_serial_sleep"] = serial / seconds
    for engine in engines:
        figures[f"{engine}_measured_needs"] = extra[engine]
    return figures


def table(figures: dict) -> str:
    """A short text table of the figures: one row per engine run."""
    med = figures.get("medians", {})
    runs = sorted({k[: -len("_trivial_s")] for k in med if k.endswith("_trivial_s")})
    lines = [
        f"{'engine':<14}{'trivial s':>10}{'sleep s':>9}{'overhead/unit s':>17}"
        f"{'speed-up':>10}{'ports':>7}  cancelled job"
    ]
    for run in runs:
        engine = run.split("_")[0]
        cancel = figures.get("cancel", {}).get(engine, {})
        said = cancel.get("outcome", "-")
        if cancel.get("starts", 0) > 1:
            said += f" (started {cancel['starts']}x)"
        ports = figures.get(f"{engine}_measured_needs", {}).get("listening_ports", "-")
        lines.append(
            f"{run:<14}{med.get(run + '_trivial_s', math.nan):>10.2f}"
            f"{med.get(run + '_sleep_s', math.nan):>9.2f}"
            f"{figures.get(run + '_overhead_per_unit_s', math.nan):>17.2f}"
            f"{figures.get(run + '_speedup_vs_serial_sleep', math.nan):>10.2f}"
            f"{ports!s:>7}  {said}"
        )
    for engine, said in figures.get("cancel", {}).items():
        lines.append(f"{engine}: {cancel_line(said)}")
    if "preempt_submitit" in figures:
        said = figures["preempt_submitit"]
        lines.append(
            f"submitit preempted (SIGTERM, USR2): {said['outcome']}"
            + _after(said.get("seconds_to_answer"))
            + f", started {said['starts']}x; 5 s after: {said.get('state_5s_after')}"
        )
    for engine, why in figures.get("skipped", {}).items():
        lines.append(f"{engine:<14}{why}")
    lines.append(f"ray           {RAY}")
    return "\n".join(lines)


def _after(seconds: float | None) -> str:
    """`` after N s`` (empty for None)."""
    return "" if seconds is None else f" after {seconds:.1f} s"


def cancel_line(said: dict) -> str:
    """One line on what an engine said of a cancelled job."""
    text = f"scancel midway: {said['outcome']}" + _after(said.get("seconds_to_answer"))
    if said["outcome"] == "no answer":
        text += " (the timeout)"
    text += f"; the unit started {said['starts']}x"
    if said.get("error"):
        text += f"; error: {said['error']}"
    gone = said.get("squeue_gone_s")
    if isinstance(gone, (int, float)):
        text += f"; squeue dropped the job after {gone:.1f} s"
    if "worker_jobs_after" in said:
        text += f"; worker jobs left: {said['worker_jobs_after']}"
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    ap.add_argument("--units", type=int, default=8)
    ap.add_argument("--sleep", type=float, default=2.0, help="seconds each sleeping unit sleeps")
    ap.add_argument("--parallelism", type=int, default=2, help="one-core jobs/workers at once")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cancel-sleep", type=float, default=15.0)
    ap.add_argument("--cancel-timeout", type=float, default=60.0)
    ap.add_argument(
        "--requeue-timeout",
        type=float,
        default=240.0,
        help="how long to wait for a requeued unit's result, seconds",
    )
    ap.add_argument("--timeout", type=float, default=180.0, help="limit of each run, seconds")
    ap.add_argument("--partition", default="debug")
    ap.add_argument(
        "--work",
        type=Path,
        default=None,
        help="folder of the jobs' files "
        "(default: a temporary one; it must be on a file system the nodes share)",
    )
    args = ap.parse_args()
    problem = slurm_problem()
    if problem:
        sys.exit(f"engines: {problem}")
    skipped = missing(args.engines)
    for why in skipped.values():
        print(why, file=sys.stderr)
    engines = [e for e in args.engines if e not in skipped]
    if not engines:
        sys.exit("engines: no engine to measure")
    work = Path(tempfile.mkdtemp(prefix="engines_", dir=args.work))
    other_jobs = subprocess.run(["squeue", "-h"], capture_output=True, text=True, check=False)
    figures: dict[str, Any] = {
        "load_average_1min_start": os.getloadavg()[0],
        "other_jobs_at_start": len(other_jobs.stdout.splitlines()),
    }
    try:
        figures |= measure_times(engines, work, args)
        cancel = {"submitit": cancel_submitit, "dask": cancel_dask}
        figures["cancel"] = {e: cancel[e](work / f"cancel_{e}", args) for e in engines}
        if "submitit" in engines:
            figures["preempt_submitit"] = preempt_submitit(work / "preempt", args)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    figures["load_average_1min_end"] = os.getloadavg()[0]
    figures["needs"] = {e: NEEDS[e] for e in engines}
    figures["skipped"] = skipped
    figures["ray"] = RAY
    print(table(figures))
    write_result("engines", figures, extra={k: v for k, v in vars(args).items() if k != "work"})


if __name__ == "__main__":
    main()
