"""Running a league's pending matches: a local pool of worker processes, or Ray tasks on a cluster."""
from __future__ import annotations

import fcntl
import json
import os
import queue
import select
import subprocess
import threading
import time
from pathlib import Path

from ..atomic import write_bytes
from .config import REPLAYS, SUBMISSIONS, WORKER_STARTUP_TIMEOUT, LeagueConfig, LeagueError, load_config
from .schedule import sync_schedule
from .store import check_writable, connect, pending_matches, record_attempt_failure, record_result
from .worker import _worker_command, _worker_env, run_match

RUN_LOCK = "run.lock"


class _Worker:
    """A worker subprocess the league parent talks to over pipes; killed and replaced when it fails."""

    def __init__(self):
        self.proc = subprocess.Popen(_worker_command() + ["--serve"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=_worker_env(), bufsize=0)
        self.buffer = b""
        self.ready = False

    def request(self, request: dict, timeout: float) -> dict:
        """Send a request and wait up to `timeout` s; raises _WorkerFailed if it dies or hangs.

        The clock starts once the worker has started up (imports are not the match's time)."""
        if not self.ready:
            if not self._read_line(WORKER_STARTUP_TIMEOUT, "worker start-up").get("ready"):
                raise _WorkerFailed("worker process did not start properly")
            self.ready = True
        try:
            self.proc.stdin.write((json.dumps(request) + "\n").encode())
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise _WorkerFailed(f"worker process died (exit code {self.proc.poll()})") from None
        return self._read_line(timeout, "match")

    def _read_line(self, timeout: float, what: str) -> dict:
        deadline = time.monotonic() + timeout
        fd = self.proc.stdout.fileno()
        while b"\n" not in self.buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise _WorkerFailed(f"{what} timed out after {timeout:.0f} s wall clock (worker hung); killed")
            ready, _, _ = select.select([fd], [], [], min(remaining, 1.0))
            if not ready:
                continue
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                code = self.proc.wait()
                how = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
                raise _WorkerFailed(f"worker process crashed ({how})")
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\n", 1)
        return json.loads(line)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()

    def close(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.kill()


class _WorkerFailed(Exception):
    pass


def run_league(folder, workers: int | None = None, ray_address: str | None = None, progress: bool = True) -> dict:
    """Run every pending match of the league (with the uncertainty schedule, batch after batch until it
    stops); returns {"scheduled", "ran", "failed", "pending_at_start", "wall_seconds"}."""
    folder = Path(folder).resolve()
    config = load_config(folder)
    if ray_address:
        try:
            import ray  # noqa: F401
        except ImportError:
            raise LeagueError("--ray: Ray is not installed; install it with: pip install 'multirace[ray]'") from None
    check_writable(folder)  # before the lock file is made
    lock = _exclusive_run(folder)
    try:
        conn = connect(folder)
    except LeagueError:
        lock.close()
        raise
    try:
        (folder / REPLAYS).mkdir(exist_ok=True)
        for stale in (folder / REPLAYS).glob("*.tmp"):
            stale.unlink(missing_ok=True)  # left by a killed run; the match is still pending
        start = time.perf_counter()
        stats = {"scheduled": 0, "ran": 0, "failed": 0, "pending_at_start": None}
        while True:  # the uncertainty schedule plans its next batch once the last one has its results
            schedule = sync_schedule(folder, config, conn)
            current = {row["match_id"] for row in schedule}
            todo = [(mid, spec) for mid, spec in pending_matches(conn) if mid in current]
            stats["scheduled"] = len(schedule)
            if stats["pending_at_start"] is None:
                stats["pending_at_start"] = len(todo)
            if not todo:
                break
            if ray_address:
                _run_on_ray(folder, config, conn, todo, ray_address, stats, progress)
            else:
                _run_local(folder, config, conn, todo, workers or os.cpu_count() or 1, stats, progress)
        stats["wall_seconds"] = round(time.perf_counter() - start, 3)
        return stats
    finally:
        conn.close()
        lock.close()  # releases the lock (so does the kernel, if this process is killed)


def _exclusive_run(folder: Path):
    """Hold the league's run lock (an flock on `run.lock`): a second `league run` would duplicate work."""
    lock = open(folder / RUN_LOCK, "a+")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "another process"
        lock.close()
        raise LeagueError(f"{folder}: another `multirace league run` is running on this league ({holder}); "
                          "wait for it to finish (running it again afterwards resumes where it stopped)") from None
    lock.truncate(0)
    lock.write(f"pid {os.getpid()}")
    lock.flush()
    return lock


def _progress_bar(total: int, enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    return Progress(TextColumn("league"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), TextColumn("{task.description}"), disable=not enabled,
                    transient=False)


def _run_local(folder: Path, config: LeagueConfig, conn, todo, n_workers: int, stats: dict, progress: bool):
    jobs: queue.Queue = queue.Queue()
    for item in todo:
        jobs.put(item)
    done: queue.Queue = queue.Queue()
    stop = threading.Event()

    def slot():
        worker = None
        try:
            while not stop.is_set():
                try:
                    match_id, spec = jobs.get(timeout=0.2)
                except queue.Empty:
                    continue
                replay = str(folder / REPLAYS / f"{match_id}.rrd") if config.replays else None
                request = {"op": "match", "spec": spec, "folder": str(folder), "replay": replay,
                           "image_every": config.replay_image_every}
                try:
                    if worker is None:
                        worker = _Worker()
                    answer = worker.request(request, config.match_timeout)
                except (_WorkerFailed, OSError, ValueError) as exc:  # died, hung, or spoke garbage
                    if worker is not None:
                        worker.kill()
                    worker = None
                    answer = {"ok": False, "error": str(exc) if isinstance(exc, _WorkerFailed)
                              else f"worker failed: {type(exc).__name__}: {exc}"}
                done.put((match_id, spec, answer, replay))
        finally:
            if worker is not None:
                worker.close()

    with _progress_bar(len(todo), progress) as bar:
        task = bar.add_task("", total=len(todo))
        threads = [threading.Thread(target=slot, daemon=True) for _ in range(max(1, min(n_workers, len(todo))))]
        for t in threads:
            t.start()
        outstanding = len(todo)
        try:
            while outstanding:
                match_id, spec, answer, replay = done.get()
                if answer.get("ok"):
                    record_result(conn, match_id, answer["result"],
                                  os.path.relpath(replay, folder) if replay else None, answer.get("wall_seconds"))
                    stats["ran"] += 1
                    outstanding -= 1
                    bar.advance(task)
                elif record_attempt_failure(conn, match_id, answer.get("error", "unknown error"),
                                            config.max_retries):
                    stats["failed"] += 1
                    outstanding -= 1
                    bar.advance(task)
                else:
                    jobs.put((match_id, spec))  # retry it (on a fresh worker if the old one failed)
                bar.update(task, description=f"{stats['failed']} failed" if stats["failed"] else "")
        finally:
            stop.set()
        for t in threads:
            t.join(timeout=10)


def _ray_match(spec: dict, files: dict, want_replay: bool, image_every: int):
    """A Ray task: run one match in a scratch folder holding its agent files; (result, replay bytes, seconds)."""
    import tempfile

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="multirace-league-") as scratch:
        scratch = Path(scratch)
        (scratch / SUBMISSIONS).mkdir()
        for rel, data in files.items():
            (scratch / rel).write_bytes(data)
        replay = scratch / "match.rrd" if want_replay else None
        result = run_match(spec, scratch, str(replay) if replay else None, image_every)
        data = replay.read_bytes() if replay else None
    return json.loads(json.dumps(result, default=float)), data, time.perf_counter() - start


def _run_on_ray(folder: Path, config: LeagueConfig, conn, todo, address: str, stats: dict, progress: bool):
    """Run pending matches as Ray tasks (agent files shipped as bytes; results written here, one transaction each)."""
    try:
        import ray
    except ImportError:
        raise LeagueError("--ray: Ray is not installed; install it with: pip install 'multirace[ray]'") from None
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}})
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_ray_match)
        file_refs = {}
        slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        queue_ = list(todo)
        running = {}  # ObjectRef -> (match_id, spec, started)

        def launch(match_id, spec):
            files = {}
            for e in spec["entrants"]:
                if not e["spec"].startswith("bot:"):
                    if e["spec"] not in file_refs:
                        file_refs[e["spec"]] = (folder / e["spec"]).read_bytes()
                    files[e["spec"]] = file_refs[e["spec"]]
            ref = task.remote(spec, files, config.replays, config.replay_image_every)
            running[ref] = (match_id, spec, time.monotonic())

        with _progress_bar(len(todo), progress) as bar:
            bar_task = bar.add_task("ray", total=len(todo))
            while queue_ or running:
                while queue_ and len(running) < slots:
                    launch(*queue_.pop(0))
                ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
                finished = []
                for ref in ready:
                    match_id, spec, _ = running.pop(ref)
                    try:
                        result, replay_bytes, seconds = ray.get(ref)
                        finished.append((match_id, spec, {"ok": True, "result": result, "wall_seconds": seconds},
                                         replay_bytes))
                    except Exception as exc:  # the task raised, or its worker crashed
                        finished.append((match_id, spec, {"ok": False, "error": f"ray task failed: "
                                                          f"{type(exc).__name__}: {str(exc)[:300]}"}, None))
                now = time.monotonic()
                for ref, (match_id, spec, started) in list(running.items()):
                    if now - started > config.match_timeout:
                        ray.cancel(ref, force=True)
                        running.pop(ref)
                        finished.append((match_id, spec, {"ok": False, "error": f"match timed out after "
                                         f"{config.match_timeout:.0f} s wall clock (ray task cancelled)"}, None))
                for match_id, spec, answer, replay_bytes in finished:
                    if answer["ok"]:
                        replay = None
                        if replay_bytes is not None:
                            final = write_bytes(folder / REPLAYS / f"{match_id}.rrd", replay_bytes)
                            replay = f"{REPLAYS}/{final.name}"
                        record_result(conn, match_id, answer["result"], replay, answer["wall_seconds"])
                        stats["ran"] += 1
                        bar.advance(bar_task)
                    elif record_attempt_failure(conn, match_id, answer["error"], config.max_retries):
                        stats["failed"] += 1
                        bar.advance(bar_task)
                    else:
                        queue_.append((match_id, spec))
    finally:
        ray.shutdown()
