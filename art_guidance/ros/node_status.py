"""The guidance node's own state beyond its plans: its learned model as loaded
(`load_model`, `model_values`), the lifecycle requests it refuses (`guard_change_state`) and
the counts of the fixes it received (`fix_counts`)."""
from __future__ import annotations

from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState

from art_guidance.guidance.core import GuidanceCore


def load_model(params: Any, log: Any) -> tuple[object | None, str]:
    """Load the learned warm start named by the node parameters `params` (`model_path`,
    `art_runtime`, `chance_constrained`) once, at start-up (never in a callback).

    Returns (provider or None, status in words). A missing, corrupt or mismatched model, an
    unknown runtime or one that is not installed leaves the node in CVX-only mode with one
    warning on `log` (and the status in every plan diagnostic); it never stops the node.
    """
    spec = params.model_path
    if spec.strip().lower() == "none":
        return None, "cvx-only: model_path is 'none'"
    try:
        from art_guidance.art.provider import ArtWarmStart, resolve_model_path

        provider = ArtWarmStart.load(resolve_model_path(spec, params.chance_constrained),
                                     runtime=params.art_runtime)
    except Exception as exc:  # a model never takes the node down
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        status = f"cvx-only: the model did not load ({type(exc).__name__}: {text[:300]})"
        log.warning(f"learned warm start unavailable, planning from CVX only: {text}")
        return None, status
    log.info(f"learned warm start: {provider.describe()}, loaded in {provider.load_ms:.0f} ms")
    status = f"loaded {provider.describe()} in {provider.load_ms:.0f} ms"
    if provider.note:
        log.warning(f"learned warm start: {provider.note}")
        status = f"{status} ({provider.note})"
    return provider, status


def prepare_numerics(numerics: str, log: Any) -> str:
    """Choose the per-step numerics and load the kernels through their door
    (`kernels.prepare`), never waiting for a compile: on a cold cache the node plans on the
    numpy path (the oracle: the same decisions) while a background process compiles them, and
    switches when they are ready (`numerics_values` tells the diagnostics). Returns the status
    in words (logged; a warning where the numpy path is taken for want of the kernels)."""
    from art_guidance import kernels

    status = f"numerics: {kernels.prepare(numerics)}"
    if numerics == "compiled" and kernels.error():
        log.warning(status)
    else:
        log.info(status)
    return status


def numerics_values(numerics: str) -> tuple[bool, str, dict]:
    """(OK: the numerics configured are in use, the status in words, the key-values) of the
    `art_guidance/numerics` diagnostic; on a cold cache not OK until the kernels are ready."""
    from art_guidance import kernels

    in_use = kernels.compiled()
    return in_use == (numerics == "compiled"), f"numerics: {kernels.status()}", {
        "numerics": "compiled" if in_use else "numpy",
        "kernels_ready_s": round(kernels.ready_s() or 0.0, 3),
        "cache": kernels.cache_note()}


def model_values(provider: Any, status: str) -> dict:
    """The model's key-values for the diagnostics."""
    values = {"model": status}
    if provider is not None:
        values.update(model_sha256=provider.sha256, model_load_ms=round(provider.load_ms, 1),
                      art_runtime=provider.runtime, art_runtime_sha256=provider.runtime_sha256)
    return values


def guard_change_state(node: Any) -> None:
    """Make a lifecycle node's `change_state` service refuse a transition its current state
    does not offer (deactivate while unconfigured, an unknown id, anything once finalized):
    success=False and a warning naming the transition, the state and the valid ones.

    rclpy's own handler (Jazzy) raises RCLError "Transition is not registered" for such a
    request, out of the executor's spin and the node's main loop; the guard answers it
    instead. A valid transition goes to rclpy's handler (which runs the on_* callback). A node
    without lifecycle services is left as it is."""
    service = getattr(node, "_service_change_state", None)
    if service is None:
        return
    rclpy_handler = service.callback

    def on_change_state(request: ChangeState.Request,
                        response: ChangeState.Response) -> ChangeState.Response:
        state_id, state = node._state_machine.current_state
        offered = {tid: label for tid, label, *_ in node._state_machine.available_transitions}
        tid, label = request.transition.id, request.transition.label
        valid = label in offered.values() if label else tid in offered
        if not valid:
            named = repr(label) if label else f"{transition_name(tid)} (id {tid})"
            choices = ", ".join(f"{name} (id {i})" for i, name in sorted(offered.items()))
            node.get_logger().warning(
                f"lifecycle transition {named} refused: not valid in state {state!r} (id "
                f"{state_id}); valid there: {choices or 'none'}")
            response.success = False
            return response
        try:
            return rclpy_handler(request, response)
        except Exception as exc:  # a service callback is a boundary: answer, never raise
            node.get_logger().error(f"lifecycle transition {label or tid} from {state!r} "
                                    f"failed: {type(exc).__name__}: {exc}")
            response.success = False
            return response

    service.callback = on_change_state


def transition_name(transition_id: int) -> str:
    """The lifecycle_msgs/Transition constant named `transition_id` (lower case, without its
    TRANSITION_ prefix), or "unknown"."""
    for name in dir(Transition):
        if name.startswith("TRANSITION_") and getattr(Transition, name) == transition_id:
            return name.removeprefix("TRANSITION_").lower()
    return "unknown"


def fix_counts(core: GuidanceCore) -> dict[str, int]:
    """What became of the fixes since configure: `fixes_received` (reached the nav callback;
    fixes a best-effort subscription dropped never do), `fixes_rejected` (of those), and of the
    replans decided, `replans_superseded` (a queued replan replaced by a newer one, never
    solved), `plans_solved` (nav- and request-triggered), and the end game's
    `replans_kept_in_force` (replans the plan in force made unnecessary) and `replans_capped`
    (solved, left out of force by the cost cap)."""
    stats = dict(core.stats)
    return {"fixes_received": stats["nav"], "fixes_rejected": stats["rejected"],
            "replans_superseded": stats["superseded"], "plans_solved": stats["plans"],
            "replans_kept_in_force": stats["kept"], "replans_capped": stats["capped"]}
