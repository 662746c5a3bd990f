"""One replayed solve against its record: the numerics path it is replayed on, the learned
step (rollout, post hoc decision, warm start kept) and the window (`record.replay`)."""
from __future__ import annotations

import json

import numpy as np

from art_guidance import kernels

ROLLOUT_ABS_TOL_MPS = 1e-6  # largest ART rollout control difference [m/s] (same model, CPU)
MIXED_NUMERICS = ("recorded while the kernels became ready: part of it on the numpy path, "
                  "part compiled")
NO_COMPILED = "recorded on the compiled path, which is not available here"


def recorded_path(record: object, configured: str | None) -> str:
    """The numerics path to replay a solve on: the record's (`numerics`), the `configured` one
    for records before the field (None: no configuration, ""); or MIXED_NUMERICS, a solve
    that cannot be replayed faithfully (whether the compiled path can be used here is asked
    where it is set, `record.replay`)."""
    recorded = str(getattr(record, "numerics", ""))
    if recorded == "mixed":
        return MIXED_NUMERICS
    if recorded not in kernels.NUMERICS:
        return "" if configured is None else configured
    return recorded


def window_rows(record: object, result: object) -> dict:
    """The window of one solve (recorded vs replayed): the same end node and target source
    (a record from before windows, or not windowed, has none)."""
    text = str(getattr(record, "window_json", "") or "")
    recorded = json.loads(text) if text else None
    replayed = None if result.window is None else result.window.to_json()
    same = (recorded is None) == (replayed is None) and (recorded is None or all(
        recorded.get(k) == replayed[k] for k in ("window_nodes", "end_node", "target_source")))
    return {"window_target": None if recorded is None else recorded.get("target_source"),
            "replayed_window_target": None if replayed is None else replayed["target_source"],
            "window_match": bool(same)}


def art_rows(record: object, result: object) -> dict:
    """Rollout and decision comparison of one solve (recorded vs replayed)."""
    rec_dv = np.asarray(getattr(record, "warm_start_art_dv_rtn_mps", []), float)
    rep_dv = (np.asarray(result.art_dv_rtn_mps, float).reshape(-1)
              if result.art_dv_rtn_mps is not None else np.zeros(0))
    row = {"warm_start": getattr(record, "warm_start", ""),
           "replayed_warm_start": result.warm_start.value,
           "replayed_warm_start_reason": result.warm_start_reason}
    ok = not row["warm_start"] or row["warm_start"] == result.warm_start.value
    if rec_dv.size or rep_dv.size:
        d_roll = (float(np.max(np.abs(rec_dv - rep_dv))) if rec_dv.shape == rep_dv.shape
                  else float("inf"))
        ph = result.posthoc
        rec_ph = int(getattr(record, "posthoc", 0))
        rep_ph = 0 if ph is None else (1 if ph.accepted else 2)
        d_er = (abs(float(getattr(record, "posthoc_e_r", np.nan)) - ph.e_r)
                if ph is not None else float("nan"))
        row.update(rollout_max_abs_diff_mps=d_roll, posthoc=rec_ph, replayed_posthoc=rep_ph,
                   e_r_abs_diff=d_er)
        ok = ok and d_roll <= ROLLOUT_ABS_TOL_MPS and rec_ph == rep_ph
    row["decision_match"] = bool(ok)
    return row
