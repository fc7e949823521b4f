"""The Ray engine: the front-end and the back-end as Ray actors pinned to nodes by custom
resources, so that on real hardware

    device A (front-end):  ray start --head --node-ip-address=A_IP --resources='{"frontend": 1}'
    device B (back-end):   ray start --address=A_IP:6379 --node-ip-address=B_IP --resources='{"backend": 1}'
    device A:              edgerecon run --engine ray --address auto ...

is all it takes. Without ``--address`` the engine starts a private single-node Ray instance
bound to 127.0.0.1 that offers both resources (same code path, one machine).

Frames travel through the object store once per task: the driver puts them, the front-end
and the back-end read the same object. Actors reserve no CPU (``num_cpus=0``: a pinned actor
that holds a CPU for its lifetime starves later tasks on small nodes) and are threaded so the
back-end can push backgrounds while the front-end is busy. The back-end actor restarts when its
process dies; the front-end notices through :class:`BackendLink` and uses it again.
"""

from __future__ import annotations

import logging
from typing import Any

from edgerecon.io.dataset import Dataset
from edgerecon.optimize.controller import BisectionController
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.engine import BackendLink, SceneModel
from edgerecon.runtime.frontend import FixedController, TaskOutput
from edgerecon.runtime.messages import TaskPlan
from edgerecon.types import EdgereconError, FrameSet

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


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise EdgereconError(
            "the Ray engine needs Ray: pip install 'edgerecon[ray]' (or use --engine embedded)"
        ) from None
    return ray


class _BackendActor:
    """Actor shell around :class:`BackEnd` (thin: all logic lives in the role class)."""

    def __init__(
        self, dataset: Dataset, config: RuntimeConfig, scene: SceneModel, frontend: Any
    ) -> None:
        from edgerecon.runtime.backend import BackEnd
        from edgerecon.scene.foreground import RigForeground

        fg = RigForeground.from_states(dataset.rig, scene.states, config.foreground)
        self._frontend = frontend
        self.backend = BackEnd(
            dataset.rig, config, fg, push=self._push, initial_background=scene.initial_background
        ).start()

    def _push(self, update: Any) -> None:
        # Fire and forget: the front-end takes it between (or during) tasks.
        self._frontend.push_background.remote(update)

    def submit(self, frames_ref: list[Any]) -> None:
        ray = _ray()
        self.backend.submit(ray.get(frames_ref[0]))

    def masks(self, time_index: int, timeout: float) -> Any:
        return self.backend.masks(time_index, timeout)

    def golden(self, time_index: int, timeout: float) -> Any:
        return self.backend.golden(time_index, timeout)

    def ping(self) -> dict[str, Any]:
        return self.backend.ping()

    def inject_fault(self, kind: str, seconds: float = 0.0) -> None:
        self.backend.inject_fault(kind, seconds)


class _FrontendActor:
    """Actor shell around :class:`FrontEnd`; it talks to the back-end actor directly."""

    def __init__(
        self, dataset: Dataset, config: RuntimeConfig, controller: Any, scene: SceneModel
    ) -> None:
        from edgerecon.pipeline import warm_up
        from edgerecon.runtime.frontend import FrontEnd

        warm_up()  # in this process, before the first task is timed
        self.frontend = FrontEnd(dataset.rig, config, controller, model_states=scene.states)
        self.config = config
        self.backend: Any = None
        self.link = BackendLink(self._ping, config.backend_retry_s)

    def set_backend(self, backend: Any) -> None:
        self.backend = backend

    def _ping(self) -> dict[str, Any] | None:
        ray = _ray()
        try:
            return ray.get(self.backend.ping.remote(), timeout=_RPC_GRACE_S)
        except ray.exceptions.RayError:
            return None
        except TimeoutError:
            return None

    def _call(self, method: Any, *args: Any, timeout: float) -> Any:
        ray = _ray()
        try:
            return ray.get(method.remote(*args), timeout=timeout + _RPC_GRACE_S)
        except (ray.exceptions.RayError, TimeoutError) as exc:
            self.link.mark_lost(f"{type(exc).__name__}")
            return None

    def plan(self, time_index: int) -> TaskPlan:
        return self.frontend.next_plan(time_index)

    def push_background(self, update: Any) -> int:
        return self.frontend.push_background(update)

    def run_task(self, frames_ref: list[Any], plan: TaskPlan, task: int) -> TaskOutput:
        ray = _ray()
        frames: FrameSet = ray.get(frames_ref[0])
        t = frames.time_index
        use = self.backend is not None and self.link.usable()
        if use:
            try:
                self.backend.submit.remote(frames_ref)
            except ray.exceptions.RayError as exc:
                self.link.mark_lost(type(exc).__name__)
                use = False

        def masks(timeout: float) -> Any:
            if not use:
                return None
            reply = self._call(self.backend.masks, t, timeout, timeout=timeout)
            if reply is None:
                self.link.mark_lost(f"no masks for time {t} within {timeout:.1f} s")
            return reply

        def golden(timeout: float) -> Any:
            return self._call(self.backend.golden, t, timeout, timeout=timeout) if use else None

        out = self.frontend.process(frames, plan, masks, golden, task=task)
        if not use:
            out.metrics.degraded_reason = f"back-end lost ({self.link.lost_reason})"
        return out

    def controller_state(self) -> dict[str, Any]:
        return self.frontend.controller.to_dict()

    def status(self) -> dict[str, Any]:
        return {
            "backgrounds_received": self.frontend.backgrounds_received,
            "bg_version": self.frontend.bg_version,
            "backend_outages": self.link.outages,
            "backend": self._ping(),
        }


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
    ) -> None:
        if _is_loopback(address):
            keep_on_loopback()
        ray = _ray()
        self._started_ray = False
        if not ray.is_initialized():
            if address:
                ray.init(address=address, log_to_driver=True)
            else:
                # A private local instance: both roles on this machine, loopback only.
                ray.init(
                    num_cpus=num_cpus,
                    resources={"frontend": 1, "backend": 1},
                    include_dashboard=False,
                    _node_ip_address="127.0.0.1",
                    log_to_driver=True,
                )
            self._started_ray = True
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
        self.frontend = front_cls.options(
            num_cpus=0, resources={"frontend": 1}, max_concurrency=4
        ).remote(dataset, config, controller, self._scene_ref)
        self.backend = back_cls.options(
            num_cpus=0,
            resources={"backend": 1},
            max_concurrency=4,
            max_restarts=-1,
            max_task_retries=0,
        ).remote(dataset, config, self._scene_ref, self.frontend)
        ray.get(self.frontend.set_backend.remote(self.backend))
        ray.get(self.backend.ping.remote())  # wait until the back-end has started

    def plan(self, time_index: int) -> TaskPlan:
        ray = _ray()
        return ray.get(self.frontend.plan.remote(time_index))

    def run_task(self, frames: FrameSet, plan: TaskPlan, task: int) -> TaskOutput:
        ray = _ray()
        ref = ray.put(frames)
        return ray.get(self.frontend.run_task.remote([ref], plan, task))

    def controller_state(self) -> dict[str, Any]:
        ray = _ray()
        return ray.get(self.frontend.controller_state.remote())

    def push_background(self, update: Any) -> None:
        ray = _ray()
        ray.get(self.frontend.push_background.remote(update))

    def status(self) -> dict[str, Any]:
        ray = _ray()
        return {"engine": self.name, **ray.get(self.frontend.status.remote())}

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        """``"kill"`` kills the back-end's process (Ray restarts it); ``"stall"``/``"crash"``
        as in :meth:`BackEnd.inject_fault`."""
        ray = _ray()
        if kind == "kill":
            ray.kill(self.backend, no_restart=False)
        else:
            ray.get(self.backend.inject_fault.remote(kind, seconds))

    def close(self) -> None:
        ray = _ray()
        for actor in (self.backend, self.frontend):
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # already gone
                pass
        if self._started_ray:
            ray.shutdown()
