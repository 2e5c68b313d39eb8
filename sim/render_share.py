"""Helper processes that draw a share of a camera frame's bodies, so that one frame uses more than one core.

pybullet's TinyRenderer holds the GIL for the whole of ``getCameraImage``, so threads cannot share its work; other
processes can. Each helper holds the same scene (a ``SceneRenderer`` of the same town and seed), replays every
``sync`` of the main renderer so that its bodies get the same unique ids and poses, and draws only the bodies whose
id falls to its share (``id % count == rank``; the others have alpha 0, which TinyRenderer skips). For each frame it
renders the same camera and hands its raw buffers (RGBA, depth buffer, segmentation mask) back through shared
memory; the main renderer draws its own share meanwhile and folds the helpers' buffers into its own with
``render_kernels.merge_share``: per pixel the nearer fragment, and at equal depth the later-drawn body, as one call
over all bodies would have kept. See ``SceneRenderer`` (``processes``) for what is exact and what it costs.

The helper is a plain child process (``python -c``, not ``multiprocessing``): nothing of the caller's ``__main__``
is imported again, and it talks over a socket pair with ``multiprocessing.connection``. It exits when the main
renderer closes it or when its end of the socket closes (the main process ended).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import traceback
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

REPLY_TIMEOUT_S = 120.0  # the first reply waits for the helper's own scene build


def _shared_dir() -> str | None:
    return "/dev/shm" if os.path.isdir("/dev/shm") else None


class _Frame:
    """A memory-mapped file both processes see: a helper's RGBA, depth buffer and segmentation mask for one frame."""

    def __init__(self, pixels: int, path: str | None = None) -> None:
        self.pixels = pixels
        size = 12 * pixels
        if path is None:
            fd, path = tempfile.mkstemp(prefix="towndrive_share_", dir=_shared_dir())
            os.ftruncate(fd, size)
        else:
            fd = os.open(path, os.O_RDWR)
        self.path = path
        self.linked = True
        try:
            self.map = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        self.rgba = np.frombuffer(self.map, np.uint8, 4 * pixels, 0)
        self.depth = np.frombuffer(self.map, np.float32, pixels, 4 * pixels)
        self.seg = np.frombuffer(self.map, np.int32, pixels, 8 * pixels)

    def views(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = h * w
        return self.rgba[:4 * n].reshape(h, w, 4), self.depth[:n].reshape(h, w), self.seg[:n].reshape(h, w)

    def unlink(self) -> None:
        if self.linked:
            self.linked = False
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)


class SharePartner:
    """The main renderer's handle on one helper process (share ``rank`` of ``count``)."""

    def __init__(self, town: Any, seed: int, rank: int, count: int) -> None:
        ours, theirs = socket.socketpair()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        code = f"from towndrive.sim.render_share import serve; serve({theirs.fileno()})"
        try:
            self.proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=(theirs.fileno(),), env=env,
                                         stdin=subprocess.DEVNULL, close_fds=True)
        finally:
            theirs.close()
        self.conn = Connection(ours.detach())
        self.rank = rank
        self.draw_ms = 0.0  # the helper's CPU time for its share of the last frame (cull and getCameraImage)
        self.frame: _Frame | None = None
        self._waiting = 1  # replies owed: the "ready" after the helper built its scene
        self.conn.send(("init", town, seed, rank, count))

    def send(self, message: tuple) -> None:
        try:
            self.conn.send(message)
        except OSError as exc:
            raise RuntimeError(f"render helper process {self.rank} is gone ({exc}); see its output above") from exc

    def ask(self, camera_pose: tuple[float, float, float], camera: Any, lighting: str, lateral_m: float,
            tile_owner: np.ndarray) -> None:
        """Start the helper on its share of a frame (``collect`` fetches it); ``tile_owner``: which process draws
        each static tile."""
        pixels, path = camera.width * camera.height, None
        if self.frame is None or self.frame.pixels < pixels:
            if self.frame is not None:
                self.frame.unlink()
            self.frame = _Frame(pixels)
            path = self.frame.path
        self.send(("render", camera_pose, camera, lighting, lateral_m, tile_owner, path, self.frame.pixels))
        self._waiting += 1

    def _reply(self) -> Any:
        try:
            if not self.conn.poll(REPLY_TIMEOUT_S):
                raise RuntimeError(f"render helper process {self.rank} did not answer in {REPLY_TIMEOUT_S:.0f} s")
            kind, payload = self.conn.recv()
        except (EOFError, OSError) as exc:
            raise RuntimeError(f"render helper process {self.rank} is gone (exit code {self.proc.poll()}); "
                               "see its output above") from exc
        if kind == "error":
            raise RuntimeError(f"render helper process {self.rank} failed:\n{payload}")
        return payload

    def collect(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The helper's RGBA, depth buffer and segmentation mask of the frame last asked for."""
        while self._waiting:
            self.draw_ms = self._reply() or 0.0
            self._waiting -= 1
        assert self.frame is not None
        self.frame.unlink()  # the helper has it mapped by now; the memory goes when both let go
        return self.frame.views(h, w)


def stop_partners(partners: list[SharePartner]) -> None:
    """Close helper processes (used at ``close`` and by the renderer's finalizer)."""
    for partner in partners:
        with contextlib.suppress(OSError):
            partner.conn.send(("close",))
    for partner in partners:
        try:
            partner.proc.wait(5.0)
        except subprocess.TimeoutExpired:
            partner.proc.kill()
            partner.proc.wait()
        with contextlib.suppress(OSError):
            partner.conn.close()
        if partner.frame is not None:
            partner.frame.unlink()
    partners.clear()


def serve(fd: int) -> None:
    """A helper's loop (run in the child process): build the scene, then replay syncs and draw shares until told
    to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the main process, which closes us
    conn = Connection(fd)
    try:
        from towndrive.sim.objects import SemanticClass, snapshot_of
        from towndrive.sim.render import SceneRenderer

        _, town, seed, rank, count = conn.recv()
        renderer = SceneRenderer(town, seed, _share=(rank, count))
        conn.send(("ready", None))
        frame: _Frame | None = None
        while True:
            try:
                message = conn.recv()
            except EOFError:
                return
            kind = message[0]
            if kind == "sync":
                _, rows, lights, view = message
                objects = [snapshot_of(r[0], SemanticClass(r[1]), *r[2:]) for r in rows]
                renderer.sync(objects, lights, view)
            elif kind == "lights":
                renderer.set_light_states(message[1])
            elif kind == "render":
                _, camera_pose, camera, lighting, lateral_m, tile_owner, path, pixels = message
                if path is not None:
                    frame = _Frame(pixels, path)
                assert frame is not None
                start = time.thread_time()
                rgba, buf, seg = renderer.draw(camera_pose, camera, lighting, lateral_m, tile_owner)
                h, w = camera.height, camera.width
                out_rgba, out_buf, out_seg = frame.views(h, w)
                out_rgba[...] = np.asarray(rgba, np.uint8).reshape(h, w, 4)
                out_buf[...] = np.asarray(buf, np.float32).reshape(h, w)
                out_seg[...] = np.asarray(seg, np.int32).reshape(h, w)
                conn.send(("done", 1000.0 * (time.thread_time() - start)))
            elif kind == "close":
                renderer.close()
                return
    except BaseException:
        with contextlib.suppress(OSError):
            conn.send(("error", traceback.format_exc()))
        raise
