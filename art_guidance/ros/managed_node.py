"""The guidance node as a managed (lifecycle) node: `ManagedGuidanceNode`
(`ros2 run art_guidance guidance_managed_node`, run by `guidance_node.main`).
"""
from __future__ import annotations

from typing import Callable

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from art_guidance.errors import GuidanceError
from art_guidance.ros.node_base import GuidanceNodeBase
from art_guidance.ros.node_status import guard_change_state


class ManagedGuidanceNode(GuidanceNodeBase, LifecycleNode):
    """The guidance node as a managed (lifecycle) node, for deterministic bring-up.

    unconfigured --configure--> inactive (configuration and model loaded, recorder open,
    publishers created but silent) --activate--> active (subscribed, planning)
    --deactivate--> inactive (unsubscribed; the running solve finishes) --cleanup-->
    unconfigured (recording finished) --shutdown--> finalized.

    What a state holds follows it on every transition: leaving `active` by any way
    (deactivate, shutdown, an error) unsubscribes and stops the worker; leaving the configured
    states (cleanup, shutdown from inactive or active, an error) also finishes the recording,
    stops the proposal worker process and destroys the publishers (`_release`). A transition
    whose work raises is logged and answered as an error; `on_error` then releases everything
    and the node returns to unconfigured, ready to be configured again.

    A `change_state` request for a transition the current state does not offer (deactivate
    while unconfigured, an unknown id, anything once finalized) is refused: success=False and
    a warning naming the transition and the state; the node keeps serving.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        guard_change_state(self)

    def _run(self, name: str, work: Callable[[], None]) -> TransitionCallbackReturn:
        """One transition's work; an exception is logged (rclpy would swallow it) and answered
        ERROR, so that rclpy calls `on_error`."""
        try:
            work()
        except Exception as exc:
            self.get_logger().error(f"lifecycle {name} failed: {type(exc).__name__}: {exc}")
            return TransitionCallbackReturn.ERROR
        return TransitionCallbackReturn.SUCCESS

    def _deactivate(self) -> None:
        """Leave `active` (idempotent): unsubscribed, the worker stopped after its solve."""
        self._destroy_subscriptions()
        self._stop_worker()

    def _release(self) -> None:
        """Back to what an unconfigured node holds (idempotent): `_deactivate`, the recording
        finished, the proposal worker process stopped, the publishers destroyed."""
        self._deactivate()
        self.shutdown_worker()
        if self.out is not None:
            for pub in self.out.publishers():
                self.destroy_lifecycle_publisher(pub)
        self.core = self.out = self.pipeline = self.recording = None

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except GuidanceError as exc:
            self.get_logger().error(f"configure failed: {exc}")
            self._release()
            return TransitionCallbackReturn.FAILURE
        return self._run("configure", lambda: self._create_publishers(
            self.create_lifecycle_publisher))

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        def activate() -> None:
            self._create_subscriptions()
            self._start_worker()

        result = self._run("activate", activate)
        return result if result is not TransitionCallbackReturn.SUCCESS else (
            super().on_activate(state))

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._run("deactivate", self._deactivate)
        return result if result is not TransitionCallbackReturn.SUCCESS else (
            super().on_deactivate(state))

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._run("cleanup", self._release)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._run(f"shutdown from {state.label}", self._release)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._release()
        except Exception as exc:  # finalized: nothing is left that could plan
            self.get_logger().error(f"lifecycle error processing failed, the node is "
                                    f"finalized: {type(exc).__name__}: {exc}")
            return TransitionCallbackReturn.FAILURE
        self.get_logger().warning(f"a lifecycle transition from {state.label!r} failed: "
                                  "everything released, the node is unconfigured")
        return TransitionCallbackReturn.SUCCESS
