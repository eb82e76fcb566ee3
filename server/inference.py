"""Where a policy slot's batched network calls run: the settings' ``inference``.

``local``: in the control loop's process (``policy.inference.LocalInference``). ``ray``: in a Ray actor
per policy version (``InferenceHost``), which loads the version from its folder on its node, on that
node's GPU when ``inference_gpus`` reserves one (``device = "cuda"`` there), and answers one call per
control tick with the whole batch: the policy's chunks, the asking signal and the shadow signals
(``policy.inference.compute``). The controller stays in the loop; the actor only computes.

Failures. Ray restarts a dead actor (``max_restarts=-1``) on any node with the resources; until it
answers again, ``RayInference.run`` raises ``InferenceUnavailable`` and the controller holds the robots
its policy drives, so the fleet holds every robot of that version and resumes by itself. The restarted
actor's signals start without per-robot state (as at each robot's next episode): a persistence count
in progress starts again. Calls are not retried: a tick's answer that comes late is a stale one.

Ray is imported only here and in ``server.ray_cluster``, and only when ``inference = "ray"``.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterable
from pathlib import Path

from policy.inference import Inference, InferenceRequest, InferenceResult, InferenceUnavailable, LocalInference
from server.ray_cluster import connect
from server.settings import Settings

CALL_TIMEOUT_S = 30.0  # a first call waits for the actor to load its policy


class InferenceHost:
    """The actor: one policy version and its signals, loaded from the version's folder."""

    def __init__(self, path: str, signal_names: list[str], device: str, trace: bool) -> None:
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        from policy.checkpoint import load_policy
        from policy.devices import prepare_for_serving
        from policy.signals import load_signal

        policy, _ = load_policy(Path(path))
        prepare_for_serving(policy, device, trace)
        signals = {name: load_signal(policy, Path(path), name) for name in signal_names}
        self.local = LocalInference(policy, signals)
        self.busy_s, self.calls = 0.0, 0

    def run(self, request: InferenceRequest, resets: list[int]) -> InferenceResult:
        t0 = time.perf_counter()
        if resets:
            self.local.reset(resets)
        try:
            return self.local.run(request)
        finally:
            self.busy_s += time.perf_counter() - t0
            self.calls += 1

    def busy(self) -> tuple[float, int]:
        """(seconds spent computing, calls answered) since the actor (re)started."""
        return self.busy_s, self.calls

    def pid(self) -> int:
        return os.getpid()


class RayInference(Inference):
    """One ``InferenceHost`` actor for a policy version; resets are sent with the next call."""

    def __init__(self, settings: Settings, path: Path, signal_names: list[str]) -> None:
        self.ray = connect(settings.ray)
        gpus = settings.inference.gpus
        actor = self.ray.remote(InferenceHost).options(
            num_cpus=settings.inference.cpus,
            num_gpus=gpus,
            max_restarts=-1,
            max_task_retries=0,
            namespace=settings.ray.namespace,
        )
        device = "cuda" if gpus > 0 else settings.inference.device
        trace = settings.inference.trace_policies
        self.handle = actor.remote(str(Path(path).resolve()), list(signal_names), device, trace)
        self._resets: list[int] = []
        self.failures = 0  # calls that found the actor unavailable
        self.overhead_s = 0.0  # time in Ray's API and waiting for answers, all calls

    def run(self, request: InferenceRequest) -> InferenceResult:
        from ray.exceptions import GetTimeoutError, RayActorError

        resets, self._resets = self._resets, []
        t0 = time.perf_counter()
        try:
            return self.ray.get(self.handle.run.remote(request, resets), timeout=CALL_TIMEOUT_S)
        except (RayActorError, GetTimeoutError) as exc:  # ActorDiedError, ActorUnavailableError are RayActorErrors
            self._resets = resets + self._resets  # not applied: sent again with the next call
            self.failures += 1
            raise InferenceUnavailable(f"the inference actor did not answer: {type(exc).__name__}") from exc
        finally:
            self.overhead_s += time.perf_counter() - t0

    def reset(self, robot_ids: Iterable[int]) -> None:
        self._resets.extend(int(i) for i in robot_ids)

    def close(self) -> None:
        with contextlib.suppress(Exception):  # already gone, or Ray shut down first
            self.ray.kill(self.handle, no_restart=True)


def make_inference(settings: Settings, path: Path, policy, signals: dict) -> Inference:
    """The back end the settings name for a slot of ``policy`` (loaded from ``path``) and ``signals``."""
    if settings.inference.backend == "ray":
        return RayInference(settings, path, list(signals))
    return LocalInference(policy, signals)
