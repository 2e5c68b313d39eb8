"""Episodes as independent, seeded work items, run on worker processes with retries, one progress bar.

Why: an evaluation, a recording or a scenario suite is a list of episodes that share nothing but the driver's code.
Each work item (``evaluation.EvalEpisode``, ``scenarios.ScenarioItem``, the CLI's ``RecordEpisode``) is a small
frozen dataclass that holds all its episode needs (driver, config, seed, reset options, rules), so it gives the same
result whichever process runs it, in whatever order; the results are merged in item order, and a parallel run's
report is the serial run's.

How the workers run, and why:

- One process per worker, started with the ``spawn`` context: pybullet (its renderer's GL state) and torch's
  thread pools do not survive ``fork``.
- Each worker builds its driver once (models loaded once) from a ``DriverSpec``, a picklable factory: this
  layer never imports ``agent`` (docs/design.md), so the command line, which may, hands the factory in. The
  worker keeps one simulator (``Worker.env``) and reuses it while the config stays the same.
- Numeric libraries get one thread per worker: ``OMP_NUM_THREADS`` and its siblings are in the environment the
  worker is spawned with (they must be set before numpy and torch load), and once the driver is built torch and
  OpenCV are told again. N workers then use N cores, not N times every core.
- Each worker has its own pipe, so the parent always knows which episode a worker holds. A worker that dies
  (``os._exit``, SIGKILL, a segfault in native code) is seen by its process sentinel and a fresh worker takes
  its place; its episode is retried once, and if it fails again it is a failed result with the error
  (``item.failed``), never dropped. An exception inside an episode counts the same way, and its retry goes to
  another worker than the one it failed on.
- ``run_ray`` runs the same items as Ray actor tasks (a local Ray cluster, or an existing one), with the same
  retry rule and the same bar; Ray is an optional extra (``towndrive[cluster]``).
- Items that make files the user asked for (``FileItem``: a recorded episode) must have them land in the user's
  folder on the machine that started the run, even when the episode ran on another node. Under Ray a worker
  therefore records into a scratch folder of its own node and the parent pulls each finished file in chunks
  through Ray's object store, writes it as ``.partial`` and renames it into place, then has the worker delete its
  copy; with ``shared_dir`` (a folder every node sees) workers write there and the parent only moves the finished
  files into place. Either way only finished files arrive, each atomically, and Ctrl-C keeps those that did.
- Workers ignore SIGINT: Ctrl-C (or the caller's ``should_stop``) reaches the parent, which stops every worker
  with SIGTERM (raised in the worker as ``SystemExit``, so a recording discards its ``.partial``) and raises
  ``Interrupted`` with the episodes that finished.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import shutil
import signal
import sys
import tempfile
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from tqdm import tqdm

if TYPE_CHECKING:
    from towndrive.agent.drivers import Driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS")
ATTEMPTS = 2  # an episode runs at most twice: once, and once more after a crash
STARTUP_DEATHS = 3  # workers that die before building their driver, more and the run stops (nothing could run)
STOP_GRACE_S = 10.0  # how long a stopped worker may take to clean up before it is killed
CHUNK_BYTES = 8 * 2**20  # a shipped file travels through Ray's object store in pieces of this size
CHUNKS_IN_FLIGHT = 4  # pieces asked for ahead of the one being written (bounds the object store's share)


def parse_workers(text: str | int) -> int:
    """``--workers``: a positive number, or ``auto`` for the cores this process may run on."""
    if str(text).strip().lower() == "auto":
        return available_cores()
    try:
        n = int(text)
    except ValueError:
        raise ValueError(f"--workers {text!r}: give a number of worker processes (1 or more) or 'auto'.") from None
    if n < 1:
        raise ValueError(f"--workers {n}: give 1 or more worker processes, or 'auto'.")
    return n


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, which a container or ``taskset`` may narrow)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class DriverSpec:
    """How to build a driver in another process: ``factory(name, **kwargs)``. The factory must be picklable (a
    module-level function such as ``towndrive.agent.drivers.make_driver``) and so must the arguments."""

    name: str
    factory: Callable[..., Driver]
    kwargs: tuple[tuple[str, Any], ...] = ()

    @classmethod
    def of(cls, factory: Callable[..., Driver], name: str, **kwargs: Any) -> DriverSpec:
        return cls(name, factory, tuple(sorted(kwargs.items())))

    def build(self) -> Driver:
        return self.factory(self.name, **dict(self.kwargs))


def start_episode(driver: Any, index: int) -> None:
    """Tell the driver which episode of the run comes next: a driver with per-episode randomness (the autopilot's
    steering noise) seeds it from the index, so an episode is the same on any worker, and serially."""
    hook = getattr(driver, "set_episode_index", None)
    if callable(hook):
        hook(index)


class Worker:
    """What one worker process keeps between episodes: its driver and its one simulator."""

    def __init__(self, driver: Driver) -> None:
        self.driver = driver
        self._env: DriveEnv | None = None
        self._key: tuple[DriveConfig, str | None] | None = None

    def env(self, config: DriveConfig, render_mode: str | None = "rgb_array") -> DriveEnv:
        """The worker's env for ``config``, built on first use and kept while the config stays the same."""
        from towndrive.envs.drive_env import DriveEnv

        key = (config, render_mode)
        if self._env is None or self._key != key:
            self.close()
            self._env, self._key = DriveEnv(config, render_mode=render_mode), key
        return self._env

    def start_episode(self, index: int) -> None:
        start_episode(self.driver, index)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env, self._key = None, None


class WorkItem(Protocol):
    """One episode: ``run`` gives its result on a worker, ``failed`` the result that stands for it when it
    could not be run (the error, counted as zero)."""

    index: int

    def run(self, worker: Worker) -> Any: ...

    def failed(self, error: str) -> Any: ...


class FileItem(WorkItem, Protocol):
    """A work item whose product is files in a folder of the user's (a recorded episode's HDF5 file).

    ``files()``: where its finished files belong, on the machine that started the run; ``writing_into(folder)``:
    the same episode writing them into ``folder`` instead, in the same order, with the same result (which still
    names the home paths). A file exists under its name only once it is finished."""

    def files(self) -> tuple[Path, ...]: ...

    def writing_into(self, folder: Path) -> FileItem: ...


def is_file_item(item: Any) -> bool:
    return callable(getattr(item, "writing_into", None)) and callable(getattr(item, "files", None))


class Interrupted(Exception):
    """Ctrl-C or a stop request: ``results`` holds the finished episodes by index."""

    def __init__(self, results: dict[int, Any], total: int) -> None:
        self.results, self.total = results, total
        super().__init__(f"interrupted: {len(results)} of {total} episode(s) finished")


@dataclass
class RunSummary:
    """What happened besides the results: failed episodes (index -> error) and how many attempts were retried."""

    failed: dict[int, str] = field(default_factory=dict)
    retried: int = 0
    wall_s: float = 0.0
    shipped: dict[str, str] = field(default_factory=dict)  # home path -> the worker's copy it came from (Ray)
    shipped_bytes: int = 0


def describe(exc: BaseException) -> str:
    """An exception as one line: its type, message and where it was raised (file:line)."""
    import traceback

    where = ""
    frames = traceback.extract_tb(exc.__traceback__)
    if frames:
        last = frames[-1]
        where = f" (at {os.path.basename(last.filename)}:{last.lineno})"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}{where}" if text else f"{type(exc).__name__}{where}"


def run_serial(items: Sequence[WorkItem], driver: Driver) -> list[Any]:
    """Run the items here, one after the other, with one driver (the serial path: errors propagate)."""
    worker = Worker(driver)
    try:
        return [item.run(worker) for item in items]
    finally:
        worker.close()


def run_parallel(items: Sequence[WorkItem], driver: DriverSpec, workers: int, desc: str = "episodes",
                 should_stop: Callable[[], bool] | None = None, summary: RunSummary | None = None,
                 progress: bool = True) -> list[Any]:
    """Run ``items`` on ``workers`` processes; the results in item order (a failed item gives ``item.failed``).

    Raises ``Interrupted`` on Ctrl-C or when ``should_stop()`` turns true, and ``RuntimeError`` when a worker
    cannot build its driver (a missing model: nothing could run)."""
    books = _Books(items, summary, desc, progress)
    n = len(items)
    ctx = mp.get_context("spawn")
    pending, results, settle = books.pending, books.results, books.settle
    slots: list[_Slot] = []
    startup_deaths = 0
    tried_on: dict[int, int] = {}  # episode -> the worker (pid) of its last attempt

    def start() -> None:
        slots.append(_Slot.start(ctx, driver))

    try:
        for _ in range(min(workers, n)):
            start()
        while not books.done:
            if should_stop is not None and should_stop():
                raise KeyboardInterrupt
            for slot in slots:
                if slot.ready and slot.index is None and pending:
                    # a retry goes to another worker than the one it failed on, unless this is the only one
                    choice = next((i for i in pending if tried_on.get(i) != slot.process.pid or len(slots) == 1), None)
                    if choice is not None:
                        pending.remove(choice)
                        slot.give(choice, items)
            ready = wait([s.conn for s in slots] + [s.process.sentinel for s in slots], timeout=0.5)
            for slot in list(slots):
                if slot.conn in ready:
                    try:
                        message = slot.conn.recv()
                    except (EOFError, OSError):
                        message = None
                    if message is not None:
                        kind = message[0]
                        if kind == "ready":
                            slot.ready = True
                        elif kind == "fatal":
                            raise RuntimeError(f"a worker could not start its driver: {message[1]}")
                        else:  # ("done", index, result) or ("error", index, text)
                            _, index, payload = message
                            slot.index = None
                            tried_on[index] = slot.process.pid
                            settle(index, payload if kind == "done" else None, payload if kind == "error" else None)
                        continue
                if slot.conn in ready or slot.process.sentinel in ready:
                    if slot.process.is_alive() and slot.conn not in ready:
                        continue
                    slot.process.join(1.0)
                    slots.remove(slot)
                    if not slot.ready:  # died before its driver was built: a broken start, not an episode's fault
                        startup_deaths += 1
                        if startup_deaths > STARTUP_DEATHS:
                            raise RuntimeError(f"worker processes die while starting "
                                               f"({_exit_text(slot.process.exitcode)}); see the errors above.")
                    if slot.index is not None:
                        _drop_partials(items[slot.index])  # what the dead worker was writing, so the retry can
                        settle(slot.index, None, f"the worker process died ({_exit_text(slot.process.exitcode)})")
                    if len(slots) < min(workers, n - len(results)):
                        start()  # a fresh worker takes the dead one's place
    except KeyboardInterrupt:
        books.close()
        _stop(slots)
        raise Interrupted(results, n) from None
    except BaseException:
        books.close()
        _stop(slots)
        raise
    books.close()
    for slot in slots:
        slot.finish()
    return books.ordered()


LOCAL_RAY = "local"  # ``--ray`` without an address: start a local Ray cluster


def run_items(items: Sequence[WorkItem], driver: DriverSpec, workers: int, desc: str = "episodes",
              should_stop: Callable[[], bool] | None = None, summary: RunSummary | None = None,
              ray: str | None = None, progress: bool = True, shared_dir: Path | None = None) -> list[Any]:
    """``run_parallel`` on local processes, or with ``ray`` (an address, or ``LOCAL_RAY``) ``run_ray``
    (``shared_dir``: see there; local workers write the user's folder directly)."""
    if ray is not None:
        return run_ray(items, driver, workers, None if ray == LOCAL_RAY else ray, desc, should_stop, summary, progress,
                       shared_dir)
    return run_parallel(items, driver, workers, desc, should_stop, summary, progress)


def run_ray(items: Sequence[WorkItem], driver: DriverSpec, workers: int, address: str | None = None,
            desc: str = "episodes", should_stop: Callable[[], bool] | None = None, summary: RunSummary | None = None,
            progress: bool = True, shared_dir: Path | None = None) -> list[Any]:
    """The same work items as Ray actor tasks: ``address`` an existing cluster (``auto``, ``ray://host:10001``),
    or None to start a local cluster with ``workers`` CPUs here (stopped at the end). One actor per worker (one CPU
    each; ``workers`` 1 on a cluster: one per CPU of the cluster) builds its driver once and keeps its simulator.
    An actor that dies takes its episode with it to a fresh actor once, as a local worker's does.

    ``FileItem``s (recorded episodes) come home: without ``shared_dir`` each is recorded into a scratch folder on
    its worker's node and its finished file is pulled here in chunks through the object store, written as
    ``.partial`` and renamed into place, and the worker's copy deleted (``summary.shipped``); with ``shared_dir``, a
    folder every node sees at that path, each attempt writes into a folder of its own there and the finished files
    are moved into place (a rename when it is on the same file system: give the destination folder itself to have
    workers write beside their files' homes).
    Other items write their files (clips, plots) where they run: on several machines, give an output folder every
    node sees."""
    import ray

    books = _Books(items, summary, f"{desc} (Ray)", progress)
    n = len(items)
    ship = shared_dir is None
    if shared_dir is not None:
        shared_dir = Path(shared_dir).absolute()
        shared_dir.mkdir(parents=True, exist_ok=True)
    run_id = uuid.uuid4().hex[:8]

    def attempt(index: int) -> WorkItem:
        """The item as a worker gets it: with ``shared_dir``, a file item writes into a folder of this attempt's own
        there (a retry never meets a dead worker's ``.partial``, nor two runs each other's files)."""
        item = items[index]
        if shared_dir is None or not is_file_item(item):
            return item
        folder = shared_dir / f".towndrive-{run_id}-{index}-{books.attempts[index]}"
        return item.writing_into(folder)  # type: ignore[attr-defined]

    started = False
    if not ray.is_initialized():
        runtime_env = {"env_vars": {k: "1" for k in THREAD_VARIABLES}}
        if address is None:
            ray.init(num_cpus=workers, runtime_env=runtime_env, include_dashboard=False, log_to_driver=False,
                     object_store_memory=300 * 2**20)
        else:
            ray.init(address=address, runtime_env=runtime_env, log_to_driver=False)
        started = True
    size = workers if workers > 1 or address is None else int(ray.cluster_resources().get("CPU", 1))
    actor_class = ray.remote(num_cpus=1, max_restarts=0)(_RayWorker)
    actors: list[Any] = []
    idle: list[Any] = []
    running: dict[Any, tuple[Any, int, WorkItem]] = {}

    def new_actor() -> None:
        actors.append(actor_class.remote(driver))
        idle.append(actors[-1])

    try:
        for _ in range(min(size, n)):
            new_actor()
        while not books.done:
            if should_stop is not None and should_stop():
                raise KeyboardInterrupt
            while idle and books.pending:
                actor, index = idle.pop(), books.pending.popleft()
                sent = attempt(index)
                running[actor.run.remote(sent, ship)] = (actor, index, sent)
            if not running:
                new_actor()
                continue
            ready, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
            for ref in ready:
                actor, index, sent = running.pop(ref)
                try:
                    kind, payload, shipment = ray.get(ref)
                    if kind == "done" and shipment is not None:
                        _bring_home(ray, actor, shipment, books.summary)
                    elif kind == "done" and sent is not items[index]:
                        _move_home(sent, items[index])  # type: ignore[arg-type]
                except ray.exceptions.RayActorError as exc:  # its process died (killed, out of memory, crashed)
                    books.settle(index, None, f"the Ray worker died ({' '.join(str(exc).split())[:200]})")
                    new_actor()
                    continue
                except OSError as exc:  # the file could not be written here: the episode is tried again
                    kind, payload = "error", f"bringing the episode's file home: {describe(exc)}"
                finally:
                    if sent is not items[index]:  # this attempt's folder in the shared one, moved home or not
                        shutil.rmtree(sent.files()[0].parent, ignore_errors=True)  # type: ignore[attr-defined]
                if kind == "fatal":
                    raise RuntimeError(f"a Ray worker could not start its driver: {payload}")
                books.settle(index, payload if kind == "done" else None, payload if kind == "error" else None)
                idle.append(actor)
    except KeyboardInterrupt:
        raise Interrupted(books.results, n) from None
    finally:
        books.close()
        for actor in actors:
            with contextlib.suppress(Exception):
                ray.kill(actor)
        if started:
            ray.shutdown()
    return books.ordered()


@dataclass(frozen=True)
class _Shipment:
    """Finished files a Ray worker holds for the parent: its scratch folder and (its copy, home path, bytes)."""

    scratch: str
    files: tuple[tuple[str, str, int], ...]


def _partial(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def _bring_home(ray: Any, actor: Any, shipment: _Shipment, summary: RunSummary) -> None:
    """Pull each shipped file from its worker in chunks into ``<home>.partial``, rename it into place, then have
    the worker delete its scratch copy. A ``.partial`` already there (an interrupted run's) is never overwritten."""
    try:
        for remote, home_text, size in shipment.files:
            home = Path(home_text)
            home.parent.mkdir(parents=True, exist_ok=True)
            tmp = _partial(home)
            with open(tmp, "xb") as fh:  # FileExistsError (an OSError) for a leftover: the episode fails, named
                try:
                    offsets = deque(range(0, size, CHUNK_BYTES))
                    wanted: deque[Any] = deque()
                    while offsets or wanted:
                        while offsets and len(wanted) < CHUNKS_IN_FLIGHT:
                            wanted.append(actor.read.remote(remote, offsets.popleft(), CHUNK_BYTES))
                        fh.write(ray.get(wanted.popleft()))
                    fh.flush()
                    os.fsync(fh.fileno())
                    if fh.tell() != size:
                        raise OSError(f"{remote} arrived with {fh.tell()} of its {size} bytes")
                except BaseException:
                    fh.close()
                    tmp.unlink(missing_ok=True)
                    raise
            os.replace(tmp, home)
            summary.shipped[str(home)] = remote
            summary.shipped_bytes += size
    finally:  # the worker's copy goes whether it arrived or not (a failed transfer is a retried episode)
        with contextlib.suppress(Exception):
            ray.get(actor.discard.remote(shipment.scratch))


def _drop_partials(item: WorkItem) -> None:
    """Delete the ``.partial`` files a worker that died left for a file item (it could not clean up)."""
    if is_file_item(item):
        for path in item.files():  # type: ignore[attr-defined]
            with contextlib.suppress(OSError):
                _partial(path).unlink(missing_ok=True)


def _move_home(sent: FileItem, item: FileItem) -> None:
    """Move the files a worker wrote into the shared folder to their home: a rename on the same file system, else a
    copy to ``.partial``, renamed into place, and the shared copy deleted."""
    for src, dst in zip(sent.files(), item.files(), strict=True):
        if src == dst or not src.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(src, dst)
        except OSError:  # another file system (EXDEV): copy, then rename
            tmp = _partial(dst)
            try:
                with open(src, "rb") as a, open(tmp, "xb") as b:
                    shutil.copyfileobj(a, b, CHUNK_BYTES)
                    b.flush()
                    os.fsync(b.fileno())
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
            os.replace(tmp, dst)
            src.unlink()


class _RayWorker:
    """A Ray actor: one worker (driver built once, one simulator), as a local worker process is."""

    def __init__(self, driver_spec: DriverSpec) -> None:
        self.error: str | None = None
        self.worker: Worker | None = None
        try:
            driver = driver_spec.build()
            limit_threads()
            self.worker = Worker(driver)
        except Exception as exc:
            self.error = describe(exc)

    def run(self, item: WorkItem, ship: bool = False) -> tuple[str, Any, _Shipment | None]:
        """The item's result; with ``ship`` a ``FileItem`` records into a scratch folder here, whose finished files
        the parent then pulls (``read``) and lets go (``discard``)."""
        if self.worker is None:
            return "fatal", self.error, None
        scratch: str | None = None
        try:
            if ship and is_file_item(item):
                scratch = tempfile.mkdtemp(prefix="towndrive-ship-")
                local = item.writing_into(Path(scratch))  # type: ignore[attr-defined]
                result = local.run(self.worker)
                files = tuple((str(a), str(b), a.stat().st_size)
                              for a, b in zip(local.files(), item.files(), strict=True) if a.is_file())  # type: ignore[attr-defined]
                return "done", result, _Shipment(scratch, files)
            return "done", item.run(self.worker), None
        except Exception as exc:
            if scratch is not None:
                shutil.rmtree(scratch, ignore_errors=True)
            return "error", describe(exc), None

    def read(self, path: str, offset: int, size: int) -> bytes:
        with open(path, "rb") as fh:
            fh.seek(offset)
            return fh.read(size)

    def discard(self, scratch: str) -> None:
        if os.path.basename(scratch).startswith("towndrive-ship-"):  # only ever a folder ``run`` made
            shutil.rmtree(scratch, ignore_errors=True)


class _Books:
    """A run's bookkeeping, the same for every backend: what waits, how often each item was tried, the results,
    the one progress bar (episodes done, failed, retried, ETA) and the summary."""

    def __init__(self, items: Sequence[WorkItem], summary: RunSummary | None, desc: str, progress: bool) -> None:
        self.items = items
        self.summary = summary if summary is not None else RunSummary()
        self.pending: deque[int] = deque(range(len(items)))
        self.attempts = [0] * len(items)
        self.results: dict[int, Any] = {}
        self.t0 = time.perf_counter()
        self.bar = tqdm(total=len(items), desc=desc, unit="episode", disable=not progress, mininterval=1.0,
                        dynamic_ncols=True)

    @property
    def done(self) -> bool:
        return len(self.results) == len(self.items)

    def settle(self, index: int, result: Any, error: str | None) -> None:
        """An attempt ended: keep its result, or try the item once more, or record it as failed."""
        summary = self.summary
        if error is None:
            self.results[index] = result
        else:
            self.attempts[index] += 1
            if self.attempts[index] < ATTEMPTS:
                summary.retried += 1
                self.pending.appendleft(index)
                self.bar.set_postfix(failed=len(summary.failed), retried=summary.retried, refresh=False)
                return
            summary.failed[index] = error
            self.results[index] = self.items[index].failed(error)
        self.bar.update(1)
        self.bar.set_postfix(failed=len(summary.failed), retried=summary.retried, refresh=False)

    def close(self) -> None:
        self.bar.close()
        self.summary.wall_s = time.perf_counter() - self.t0

    def ordered(self) -> list[Any]:
        return [self.results[i] for i in range(len(self.items))]


@dataclass
class _Slot:
    """One worker process as the parent sees it: its pipe, whether it has built its driver, what it holds."""

    process: Any
    conn: Connection
    ready: bool = False
    index: int | None = None

    @classmethod
    def start(cls, ctx: Any, driver: DriverSpec) -> _Slot:
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_worker_main, args=(child, driver), daemon=True, name="towndrive-worker")
        with one_thread_environment():
            process.start()
        child.close()
        return cls(process, parent)

    def give(self, index: int, items: Sequence[WorkItem]) -> None:
        self.index = index
        with contextlib.suppress(BrokenPipeError, OSError):  # a dead worker: its sentinel reports it, and the
            self.conn.send((index, items[index]))  # episode is retried

    def finish(self) -> None:
        with contextlib.suppress(BrokenPipeError, OSError):
            self.conn.send(None)
        self.process.join(STOP_GRACE_S)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


def _stop(slots: list[_Slot]) -> None:
    """Stop every worker: SIGTERM (the worker cleans up), then SIGKILL for one that does not end in time."""
    for slot in slots:
        if slot.process.is_alive():
            slot.process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for slot in slots:
        slot.process.join(max(0.0, deadline - time.monotonic()))
        if slot.process.is_alive():
            slot.process.kill()
            slot.process.join()
        slot.conn.close()


def _exit_text(code: int | None) -> str:
    if code is None:
        return "exit code unknown"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


@contextlib.contextmanager
def one_thread_environment() -> Iterator[None]:
    """The thread variables set to 1 while a worker is spawned (it inherits the environment; they must be in
    place before numpy or torch loads there), and the parent's own values back afterwards."""
    saved = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    os.environ.update({k: "1" for k in THREAD_VARIABLES})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def limit_threads() -> None:
    """One thread for the libraries already loaded in this process that keep their own pools."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
    cv2 = sys.modules.get("cv2")
    if cv2 is not None:
        cv2.setNumThreads(1)


def _terminate(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)


def _stop_with_parent() -> None:
    """A watcher thread: when the parent process is gone (killed, say), stop this worker as the parent would."""
    import threading

    parent = mp.parent_process()
    if parent is None:
        return

    def watch() -> None:
        wait([parent.sentinel])
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, daemon=True, name="towndrive-parent-watch").start()


def _worker_main(conn: Connection, driver_spec: DriverSpec) -> None:
    """A worker: build the driver once, then run the items the parent sends until it sends None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    signal.signal(signal.SIGTERM, _terminate)  # the parent's stop: unwind, so files in progress are discarded
    _stop_with_parent()
    try:
        driver = driver_spec.build()
        limit_threads()
    except Exception as exc:
        conn.send(("fatal", describe(exc)))
        return
    worker = Worker(driver)
    conn.send(("ready",))
    try:
        while True:
            try:
                message = conn.recv()
            except EOFError:
                break
            if message is None:
                break
            index, item = message
            try:
                result = item.run(worker)
            except Exception as exc:
                conn.send(("error", index, describe(exc)))
                continue
            conn.send(("done", index, result))
    finally:
        worker.close()
        close = getattr(driver, "close", None)
        if callable(close):
            close()
