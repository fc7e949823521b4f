"""The Ray engine: the front-end and the back-end as Ray actors pinned to nodes by custom
resources, so that on real hardware

    device A (front-end):  ray start --head --node-ip-address=A_IP --resources='{"frontend": 1}'
    device B (back-end):   ray start --address=A_IP:6379 --node-ip-address=B_IP --resources='{"backend": 1}'
    device A:              edgerecon run --engine ray --address auto ...

is all it takes (start each node with ``RAY_worker_niceness=0`` in its environment: Ray runs
its workers at niceness 15, below every process at the default priority, see
:func:`normal_priority`). Without ``--address`` the engine starts a private single-node Ray instance
bound to 127.0.0.1 that offers both resources (same code path, one machine); its processes
die with the driver, kill -9 included (:mod:`edgerecon.runtime.ray_reaper`). An address where
no cluster answers is an :class:`EdgereconError` within seconds (:func:`connect`).

Frames travel through the object store once per task: the driver puts them, the front-end
and the back-end read the same object. Actors reserve no CPU (``num_cpus=0``: a pinned actor
that holds a CPU for its lifetime starves later tasks on small nodes) and are threaded so the
back-end can push backgrounds while the front-end is busy. The actors are thin shells: all
logic lives in the roles and in :func:`~edgerecon.runtime.engine.run_frontend_task`, shared
with the embedded engine. The back-end actor restarts when its process dies (and is killed
for a restart when its task thread died or is stuck past the watchdog); a (re)started actor
gets its epoch from the front-end, which notices through :class:`BackendLink` and uses it
again.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from edgerecon.io.dataset import Dataset
from edgerecon.optimize.controller import BisectionController
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.engine import (
    BackendLink,
    SceneModel,
    restart_reason,
    run_frontend_task,
    start_frontend,
)
from edgerecon.runtime.frontend import FixedController, FrontEndState, TaskOutput
from edgerecon.runtime.messages import TaskPlan, TaskWork
from edgerecon.runtime.ray_reaper import start_reaper
from edgerecon.scene.foreground import RigForeground
from edgerecon.types import EdgereconError, FrameSet, PointCloud

logger = logging.getLogger(__name__)

#: Seconds added to a remote wait before the driver-side ``ray.get`` gives up.
_RPC_GRACE_S = 5.0


def _is_loopback(address: str | None) -> bool:
    if not address or address == "auto":
        return address is None
    host = address.rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1")


def keep_on_loopback() -> None:
    """Stop Ray from rewriting a loopback cluster address to the host's network interface.

    When connecting, Ray replaces 127.0.0.1 by the address its host uses to reach the outside
    (``resolve_ip_for_localhost``) unless "Ray clusters" are disabled, which is what its
    environment switch below does on Linux (it only affects that rewrite and the choice of the
    local node's IP). A cluster started with ``--node-ip-address=127.0.0.1`` listens on
    loopback only, so without this the driver cannot reach it — and test and local traffic must
    stay on loopback anyway.
    """
    import os
    import sys

    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    if "ray" in sys.modules:  # already imported: the constant is read at call time
        from ray._private import ray_constants

        ray_constants.ENABLE_RAY_CLUSTER = False


def normal_priority(target: int = 0) -> int:
    """Lower every thread of this process to niceness ``target`` (never above it); returns
    the largest niceness left.

    Ray starts its worker processes, actors included, at niceness 15 more than its raylet
    (``worker_niceness``) so that its daemons and the driver come first. For the front-end
    that puts the critical path below everything else on its node: with both roles and the
    driver on a 2-core machine (caliscope_charuco's whole capture at 40 %,
    docs/BENCHMARKS.md) the controller kept 1.6x fewer foreground points per task. A private
    instance starts its workers at the driver's niceness (:func:`connect`); on a cluster
    started without ``RAY_worker_niceness=0`` the front-end actor lowers its own niceness to
    the driver's where the OS allows it (Linux counts niceness per thread, so every thread
    of the process; lowering it needs root or ``CAP_SYS_NICE``), else it warns once."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except (FileNotFoundError, NotADirectoryError):  # not Linux: the process as a whole
        tids = [0]
    left = target
    for tid in tids:
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) > target:
                os.setpriority(os.PRIO_PROCESS, tid, target)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except OSError:  # not allowed: it stays where Ray put it
            pass
        try:
            left = max(left, os.getpriority(os.PRIO_PROCESS, tid))
        except OSError:
            continue
    return left


def use_cluster_token(environ: dict[str, str] | None = None, home: Path | None = None) -> bool:
    """Before joining a cluster at an address: ask for Ray's token authentication when a
    token is at hand and ``RAY_AUTH_MODE`` is not set; returns whether it did.

    Ray 2.59 and later start ``ray start --head`` clusters with token authentication, while a
    driver that joins one by address still defaults to ``RAY_AUTH_MODE=disabled`` and is
    refused (Ray 2.60: "Failed to connect to Ray cluster"). A driver in token mode also joins
    a cluster without authentication, so the token is used whenever one is found:
    ``RAY_AUTH_TOKEN``, the file at ``RAY_AUTH_TOKEN_PATH``, or ``~/.ray/auth_token`` (where
    ``ray start`` keeps it; ``ray get-auth-token`` prints it)."""
    env = os.environ if environ is None else environ
    if env.get("RAY_AUTH_MODE"):
        return False
    path = env.get("RAY_AUTH_TOKEN_PATH")
    token_file = (
        Path(path) if path else (Path.home() if home is None else home) / ".ray" / "auth_token"
    )
    if not env.get("RAY_AUTH_TOKEN") and not token_file.is_file():
        return False
    env["RAY_AUTH_MODE"] = "token"
    return True


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise EdgereconError(
            "the Ray engine needs Ray: pip install 'edgerecon[ray]' (or use --engine embedded)"
        ) from None
    return ray


class _BackendActor:
    """Actor shell around :class:`BackEnd` (thin: all logic lives in the role class). A
    (re)started actor finds the front-end actor by its name and registers with it: its epoch,
    and on the first start the frames of the first background.

    The constructor takes plain values only. Ray cannot be relied on to restart an actor
    whose constructor arguments live in its object store or hold references (their lineage
    is not counted, ray-project/ray#53727), and it logs an error for every such actor with
    restarts; an actor handle counts as a reference."""

    def __init__(self, dataset: Dataset, config: RuntimeConfig, frontend_name: str) -> None:
        from edgerecon.runtime.backend import BackEnd
        from edgerecon.runtime.memory import start_heap_trimmer, tune_malloc

        tune_malloc()  # a worker process of a cluster the driver did not start
        start_heap_trimmer()

        ray = _ray()
        frontend = ray.get_actor(frontend_name)
        start, initial = ray.get(frontend.register_backend.remote())
        self._frontend = frontend
        self.backend = BackEnd(
            dataset.rig,
            config,
            push=self._push,
            initial_background=initial,
            epoch=start.epoch,
        ).start()

    def _push(self, update: Any) -> None:
        # Fire and forget: the front-end takes it between (or during) tasks.
        self._frontend.push_background.remote(update)

    def submit(
        self, frames_ref: list[Any], foreground: Any, golden: bool, still_uses: Any = None
    ) -> None:
        frames = _ray().get(frames_ref[0])
        self.backend.submit(
            TaskWork(frames=frames, foreground=foreground, golden=golden, still_uses=still_uses)
        )

    def golden(self, time_index: int, timeout: float) -> Any:
        return self.backend.golden(time_index, timeout)

    def ping(self) -> dict[str, Any]:
        return self.backend.ping()

    def node_id(self) -> str:
        return str(_ray().get_runtime_context().get_node_id())

    def inject_fault(self, kind: str, seconds: float = 0.0) -> None:
        self.backend.inject_fault(kind, seconds)

    def check_calibration(self, since: int, cameras: list[str]) -> None:
        self.backend.check_calibration(since, cameras)


class _RemoteBackend:
    """:class:`BackendClient` over the back-end actor for one task (the frames travel as one
    object-store reference); a failed or late call is None and marks the back-end lost."""

    def __init__(self, actor: Any, frames_ref: Any, link: BackendLink) -> None:
        self._actor = actor
        self._ref = frames_ref
        self._link = link

    def submit(self, work: TaskWork) -> None:
        # The frames are in the object store already; the foreground (masks at the working
        # resolution) travels with the call.
        self._actor.submit.remote([self._ref], work.foreground, work.golden, work.still_uses)

    def _call(self, method: Any, *args: Any, timeout: float) -> Any:
        ray = _ray()
        try:
            return ray.get(method.remote(*args), timeout=timeout + _RPC_GRACE_S)
        except (ray.exceptions.RayError, TimeoutError) as exc:
            self._link.mark_lost(type(exc).__name__)
            return None

    def golden(self, time_index: int, timeout: float) -> Any:
        return self._call(self._actor.golden, time_index, timeout, timeout=timeout)


class _FrontendActor:
    """Actor shell around :class:`FrontEnd`; it talks to the back-end actor directly."""

    def __init__(
        self,
        dataset: Dataset,
        config: RuntimeConfig,
        controller: Any,
        scene: SceneModel,
        restored: Any,
        background: Any,
        niceness: int = 0,
    ) -> None:
        from edgerecon.runtime.memory import start_heap_trimmer, tune_malloc

        tune_malloc()  # a worker process of a cluster the driver did not start
        start_heap_trimmer()
        self.niceness = normal_priority(niceness)
        if self.niceness > niceness:
            logger.warning(
                "the Ray front-end (the critical path) runs at niceness %d, the driver at "
                "%d: start the front-end's node with RAY_worker_niceness=0 in its "
                "environment (or run as a user allowed to lower niceness)",
                self.niceness,
                niceness,
            )
        self.frontend = start_frontend(dataset, config, controller, scene, restored, background)
        self._initial_background: FrameSet | None = scene.initial_background
        self.config = config
        self.backend: Any = None
        self.link = BackendLink(self._ping, config.backend_retry_s)
        self.backend_restarts = 0

    def set_backend(self, backend: Any) -> None:
        self.backend = backend

    def register_backend(self) -> tuple[Any, FrameSet | None]:
        """A back-end actor (re)starts: its ``BackendStart`` and, on the first start, the
        frames of the first background (then released here)."""
        start = self.frontend.register_backend()
        initial, self._initial_background = self._initial_background, None
        return start, initial if start.first else None

    def _ping(self) -> dict[str, Any] | None:
        ray = _ray()
        try:
            status = ray.get(self.backend.ping.remote(), timeout=_RPC_GRACE_S)
        except (ray.exceptions.RayError, TimeoutError):
            return None  # its process is gone: Ray restarts it (max_restarts=-1)
        reason = restart_reason(status, self.config.watchdog_s)
        if reason is not None:
            logger.warning("Ray back-end %s: restarting its actor", reason)
            ray.kill(self.backend, no_restart=False)
            self.backend_restarts += 1
            return None
        return status

    def plan(self, time_index: int) -> TaskPlan:
        return self.frontend.next_plan(time_index)

    def push_background(self, update: Any) -> Any:
        return self.frontend.push_background(update)

    def pending_updates(self, time_index: int) -> list[int]:
        return self.frontend.pending_updates(time_index)

    def learn_updates(self, updates: list[FrameSet]) -> float:
        return self.frontend.learn_updates(updates)

    def inject_fault(self, kind: str) -> None:
        self.frontend.inject_fault(kind)

    def scene_model(self) -> SceneModel | None:
        model = self.frontend.scene_model()
        if model is None:
            return None
        return dataclasses.replace(model, initial_background=self._initial_background)

    def run_task(
        self,
        frames_ref: list[Any],
        plan: TaskPlan,
        task: int,
        defects: dict[str, str],
        updates: list[FrameSet],
    ) -> TaskOutput:
        frames: FrameSet = _ray().get(frames_ref[0])
        client = _RemoteBackend(self.backend, frames_ref[0], self.link)
        return run_frontend_task(
            self.frontend, self.link, client, frames, plan, task, defects, updates
        )

    def state(self) -> Any:
        return self.frontend.state()

    def node_id(self) -> str:
        return str(_ray().get_runtime_context().get_node_id())

    def status(self) -> dict[str, Any]:
        backend = self._ping()
        return {
            "frontend_niceness": self.niceness,
            "backgrounds_received": self.frontend.backgrounds_received,
            "snapshots_received": self.frontend.snapshots_received,
            "bg_version": self.frontend.bg_version.to_list(),
            "backend_outages": self.link.outages,
            "backend_restarts": self.backend_restarts,
            "abandoned_threads": self.frontend.abandoned.running()
            + list((backend or {}).get("abandoned_threads", [])),
            "backend": backend,
        }


def _time_original_here(
    frames: FrameSet, rig: Any, rc: Any, runs: int, niceness: int
) -> tuple[Any, str, str | None]:
    """A Ray task: ``online.time_original`` in a worker of the node it was placed on, at
    the niceness the front-end actor will take (:func:`normal_priority`); the node's id as
    where it ran."""
    from edgerecon.runtime.memory import tune_malloc
    from edgerecon.runtime.online import time_original

    tune_malloc()  # as the front-end actor's process
    normal_priority(niceness)
    timings, why, _ = time_original(frames, rig, rc, runs)
    return timings, why, str(_ray().get_runtime_context().get_node_id())


class FrontendTimer:
    """``online.OriginalTimer`` for a run on a Ray cluster: the original pipeline is timed
    on the node with the ``frontend`` resource, where the run's tasks will run (the node
    that starts the command may be another, slower or faster device). One Ray task in a
    worker that exits after it (``max_calls=1``: its memory goes back before the actors
    start); the frames travel from this process as a task's do."""

    def __init__(self, address: str | None) -> None:
        self.joined = connect(address) is not None
        """This timer joined the cluster (the engine takes the connection over)."""

    def __call__(
        self, frames: FrameSet, rig: Any, rc: Any, runs: int
    ) -> tuple[Any, str, str | None]:
        ray = _ray()
        if ray.cluster_resources().get("frontend", 0) < 1:
            raise EdgereconError(
                "the Ray cluster has no node with the custom resource 'frontend': start the "
                "frontend node with --resources='{\"frontend\": 1}'"
            )
        fn = ray.remote(num_cpus=0, resources={"frontend": 1}, max_calls=1, max_retries=0)(
            _time_original_here
        )
        result: tuple[Any, str, str | None] = ray.get(fn.remote(frames, rig, rc, runs, os.nice(0)))
        return result

    def release(self) -> None:
        """Leave the cluster again when this timer joined it (a measurement that failed:
        no engine takes the connection over)."""
        if self.joined:
            _ray().shutdown()
            self.joined = False


class RayEngine:
    """Front-end and back-end as Ray actors (see module docstring)."""

    name = "ray"

    def __init__(
        self,
        dataset: Dataset,
        config: RuntimeConfig,
        controller: BisectionController | FixedController,
        scene: SceneModel,
        *,
        address: str | None = None,
        num_cpus: int | None = None,
        restored: FrontEndState | None = None,
        background: PointCloud | None = None,
        joined: bool = False,
    ) -> None:
        self.config = config
        # ``joined``: a FrontendTimer joined the cluster for this run already.
        self._started_ray = connect(address, num_cpus) is not None or joined
        # A private instance dies with this process, kill -9 included (see ray_reaper).
        self._reaper = start_reaper() if self._started_ray and not address else None
        ray = _ray()
        resources = ray.cluster_resources()
        for role in ("frontend", "backend"):
            if resources.get(role, 0) < 1:
                raise EdgereconError(
                    f"the Ray cluster has no node with the custom resource {role!r}: start the "
                    f"{role} node with --resources='{{\"{role}\": 1}}'"
                )
        front_cls = ray.remote(_FrontendActor)
        back_cls = ray.remote(_BackendActor)
        self._scene_ref = ray.put(scene)
        # The models' working sizes (to reduce update frames before they travel).
        self._sizes = RigForeground.from_states(dataset.rig, scene.states, config.foreground)
        # Named, so that the back-end actor finds it (on every restart) without a handle in
        # its constructor arguments (see _BackendActor).
        name = f"edgerecon-frontend-{uuid.uuid4().hex}"
        # The last argument: the driver's niceness, the front-end's instead of the 15 more
        # that Ray gives its workers (normal_priority).
        self.frontend = front_cls.options(
            name=name, num_cpus=0, resources={"frontend": 1}, max_concurrency=4
        ).remote(
            dataset,
            config,
            controller,
            self._scene_ref,
            restored,
            background,
            os.nice(0),
        )
        self.backend = back_cls.options(
            num_cpus=0,
            resources={"backend": 1},
            max_concurrency=4,
            max_restarts=-1,
            max_task_retries=0,
        ).remote(dataset, config, name)
        ray.get(self.frontend.set_backend.remote(self.backend))
        ray.get(self.backend.ping.remote())  # wait until the back-end has started

    def plan(self, time_index: int) -> TaskPlan:
        return _ray().get(self.frontend.plan.remote(time_index))

    def pending_updates(self, time_index: int) -> list[int]:
        return list(_ray().get(self.frontend.pending_updates.remote(time_index)))

    def learn_updates(self, updates: Sequence[FrameSet]) -> float:
        if not updates:
            return 0.0
        small = [self._reduce(u) for u in updates]
        # The front-end's watchdog answers first; this bound is for a front-end gone silent.
        limit = self.config.watchdog_s + 2 * _RPC_GRACE_S
        return float(_ray().get(self.frontend.learn_updates.remote(small), timeout=limit))

    def run_task(
        self,
        frames: FrameSet,
        plan: TaskPlan,
        task: int,
        defects: Mapping[str, str],
        updates: Sequence[FrameSet] = (),
    ) -> TaskOutput:
        ray = _ray()
        ref = ray.put(frames)
        # Update frames travel reduced to the background models' working size (a few
        # percent of a full-HD frame set's bytes).
        small = [self._reduce(u) for u in updates]
        # The front-end's watchdog answers first; this bound is for a front-end gone silent.
        limit = self.config.watchdog_s + 2 * _RPC_GRACE_S
        return ray.get(
            self.frontend.run_task.remote([ref], plan, task, dict(defects), small), timeout=limit
        )

    def _reduce(self, frames: FrameSet) -> FrameSet:
        return self._sizes.reduce(frames)

    def state(self) -> FrontEndState:
        return _ray().get(self.frontend.state.remote())

    def node_ids(self) -> dict[str, str]:
        """The Ray node each role's actor runs on."""
        ray = _ray()
        return {
            "frontend": ray.get(self.frontend.node_id.remote()),
            "backend": ray.get(self.backend.node_id.remote()),
        }

    def status(self) -> dict[str, Any]:
        return {"engine": self.name, **_ray().get(self.frontend.status.remote())}

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        """``"kill"`` kills the back-end's process (Ray restarts it); ``"stall"``/``"crash"``
        as in :meth:`BackEnd.inject_fault`."""
        ray = _ray()
        if kind == "kill":
            ray.kill(self.backend, no_restart=False)
        else:
            ray.get(self.backend.inject_fault.remote(kind, seconds))

    def inject_frontend_fault(self, kind: str) -> None:
        _ray().get(self.frontend.inject_fault.remote(kind))

    def check_calibration(self, since: int, cameras: Sequence[str]) -> None:
        self.backend.check_calibration.remote(since, list(cameras))  # fire and forget

    def scene_model(self) -> SceneModel | None:
        limit = self.config.watchdog_s + 2 * _RPC_GRACE_S
        model: SceneModel | None = _ray().get(self.frontend.scene_model.remote(), timeout=limit)
        return model

    def close(self) -> None:
        ray = _ray()
        for actor in (self.backend, self.frontend):
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # already gone
                pass
        if self._started_ray:
            ray.shutdown()
        if self._reaper is not None:
            self._reaper.kill()
            self._reaper.wait()


def _check_reachable(address: str, hint: str) -> None:
    """A HOST:PORT nobody listens on fails in a second here, not after Ray's minute of
    retries."""
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not port.isdigit():
        raise EdgereconError(f"--address must be HOST:PORT or auto, got {address!r}")
    try:
        socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=3.0).close()
    except OSError as exc:
        raise EdgereconError(f"no Ray cluster at --address {address}: {hint} ({exc})") from None


def connect(address: str | None, num_cpus: int | None = None) -> Any:
    """Connect to the Ray cluster at ``address``, or start a private one on 127.0.0.1 that
    offers both roles; returns the ray module when this call started or joined a cluster
    (None when this process was already connected). No cluster at ``address`` is an
    :class:`EdgereconError` saying how to start one."""
    if _is_loopback(address):
        keep_on_loopback()
    hint = (
        "start one first (ray start --head --node-ip-address=IP "
        "--resources='{\"frontend\": 1}', see the README), or leave out --address for a "
        "private local instance"
    )
    if address:
        _check_reachable(address, hint)
        if use_cluster_token():
            hint += (
                "; this driver used the Ray token it found (RAY_AUTH_MODE=token): it must be "
                "the cluster's (`ray get-auth-token` on the head node)"
            )
    ray = _ray()
    if ray.is_initialized():
        return None
    if address:
        try:
            ray.init(address=address, log_to_driver=True)
        except ConnectionError as exc:
            raise EdgereconError(f"no Ray cluster at --address {address}: {hint} ({exc})") from None
    else:
        # A private local instance: both roles on this machine, loopback only; its workers
        # at the driver's niceness, not 15 more (normal_priority).
        ray.init(
            num_cpus=num_cpus,
            resources={"frontend": 1, "backend": 1},
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            _system_config={"worker_niceness": 0},
            log_to_driver=True,
        )
    return ray
