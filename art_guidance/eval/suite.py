"""The rollout suite of `art-guidance evaluate --suite rollouts`: a model rolled out from held-out
scenarios, judged against the CVX solution of each (C(t_1), E_R, the post hoc region), with the
oracle row (the plans' own controls through the same machinery) and the model's training
provenance beside it."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from art_guidance.config import GuidanceConfig, mode_name
from art_guidance.errors import InputError


def distribution(values: np.ndarray) -> dict:
    """min / quartiles / max / mean of a sample (JSON-ready)."""
    q = np.percentile(values, [0, 25, 50, 75, 100])
    return {"min": float(q[0]), "p25": float(q[1]), "median": float(q[2]), "p75": float(q[3]),
            "max": float(q[4]), "mean": float(np.mean(values))}


def _trained_on(art: object, data_dir: str) -> bool:
    """Whether the model's training data includes the dataset directory `data_dir`, or other
    scenarios of its seed."""
    from art_guidance.art.data import trained_manifests, trained_seed_bases
    from art_guidance.eval.inputs import dataset_info, seen

    return seen(trained_manifests(art.meta), trained_seed_bases(art.meta),
                dataset_info(data_dir))


def evaluate_model(data: dict, model_path: str, n: int | None, threads: int,
                   progress: bool = True, split: str = "test", data_dir: str | None = None,
                   oracle: bool = False, reward_scales: tuple[float, ...] = (1.0,)) -> dict:
    """Rollout suite of one model on the held-out scenarios of `data` (see `run`)."""
    import torch
    from tqdm import tqdm

    from art_guidance.art import build_safety, load
    from art_guidance.eval.scoring import heldout_scenarios, score_rollouts

    torch.set_num_threads(threads)
    art = load(model_path)
    if split == "all" and data_dir is not None and _trained_on(art, data_dir):
        raise InputError("--split", f"all scenarios of {data_dir} are not held out from "
                         f"{Path(model_path).name}: it was trained on that dataset or on "
                         "scenarios of its seed")
    held = heldout_scenarios(data, ("cvx_roe_m", "cvx_dv_rtn_mps", "dv_rtn_mps", "feasible",
                                    "cost_mps", "constraint_to_go"), split)
    m = held["index"].size if n is None else min(n, held["index"].size)
    safety = build_safety(art)
    # C_CVX(t_1) again under the current safety model (the labels may come from an older
    # pipeline version), so both sides are judged by the same evaluation
    c_cvx_now = np.array([safety.evaluate(held["cvx_roe_m"][i], held["cvx_dv_rtn_mps"][i])
                          .constraint_to_go[0] for i in range(m)])
    report_oracle = _oracle(safety, held, m, c_cvx_now) if oracle else None
    subject = GuidanceConfig.load().planning.posthoc_subject  # the sweep ranks as in flight
    t0 = time.perf_counter()
    parts, batch = [], 50
    for s in tqdm(range(0, m, batch), desc=f"rollouts {Path(model_path).name}", unit="batch",
                  disable=not progress):
        sl = slice(s, min(s + batch, m))
        parts.append(score_rollouts(art, safety, held["roe0_m"][sl], held["target_rtn"][sl],
                                    held["cvx_cost_mps"][sl], c_cvx_now[sl],
                                    batch_size=batch, reward_scales=reward_scales,
                                    subject=subject))
    wall = time.perf_counter() - t0
    c_art = np.concatenate([p.c_art for p in parts])
    c_cvx = np.concatenate([p.c_cvx for p in parts])
    e_r = np.concatenate([p.e_r for p in parts])
    accepted = np.concatenate([p.accepted for p in parts])
    return {
        "model": Path(model_path).name, "model_sha256": art.sha256,
        "representation": art.config.representation, "n_scenarios": int(m),
        "scenario_indices": [int(held["index"][0]), int(held["index"][m - 1])],
        "mode": mode_name(safety.uncertainty is not None),
        "c_art_t1": distribution(c_art), "c_cvx_t1": distribution(c_cvx),
        "c_cvx_label_agreement": float(np.mean(c_cvx == held["cvx_constraint_to_go0"][:m])),
        "frac_c_art_zero": float(np.mean(c_art == 0)),
        "frac_c_cvx_zero": float(np.mean(c_cvx == 0)),
        "frac_c_art_below_cvx": float(np.mean(c_art < c_cvx)),
        "frac_c_art_le_cvx": float(np.mean(c_art <= c_cvx)),
        "e_r": distribution(e_r), "e_r_pct_median_abs": float(np.median(np.abs(100 * e_r))),
        "e_r_pct_median": float(np.median(100 * e_r)),
        "e_r_pct_q90": float(np.percentile(100 * e_r, 90)),
        "frac_posthoc_accepted": float(np.mean(accepted)),
        "c_art_histogram": np.bincount(c_art, minlength=int(c_art.max()) + 1).tolist(),
        "wall_s": wall, "rollouts_per_s": m / wall, "threads": threads, "split": split,
        "reward_scales": list(reward_scales),
        "training": _training_summary(art),
        **({"oracle": report_oracle} if report_oracle is not None else {}),
    }


def _training_summary(art: object) -> dict:
    """What the model was trained on and how far (from its checkpoint's provenance)."""
    t = art.meta.get("training", {})
    d = art.meta.get("dataset", {})
    return {"preset": t.get("preset"), "config": art.config.to_dict(),
            "n_parameters": t.get("n_parameters"), "n_train": d.get("n_train"),
            "best_val_loss": t.get("best_val_loss"), "step": t.get("step"),
            "epoch": t.get("epoch"), "stop_reason": t.get("stop_reason"),
            "train_config": t.get("train_config")}


def _oracle(safety: object, held: dict, m: int, c_cvx_now: np.ndarray) -> dict:
    """A perfect model: the plans' own controls through the rollout machinery (`replay`)."""
    from art_guidance.eval.scoring import score_oracle

    ok = held["feasible"][:m]
    ev = score_oracle(safety, held["roe0_m"][:m][ok], held["dv_rtn_mps"][:m][ok],
                      held["cvx_cost_mps"][:m][ok], c_cvx_now[ok])
    labels_c = held["constraint_to_go"][:m][ok][:, 0]
    labels_e_r = (held["cost_mps"][:m][ok] - held["cvx_cost_mps"][:m][ok]) \
        / held["cvx_cost_mps"][:m][ok]
    return {"n_scenarios": int(ok.sum()), "frac_c_zero": float(np.mean(ev.c_art == 0)),
            "frac_c_label_agreement": float(np.mean(ev.c_art == labels_c)),
            "e_r_pct_median": float(np.median(100 * ev.e_r)),
            "e_r_pct_q90": float(np.percentile(100 * ev.e_r, 90)),
            "e_r_max_abs_diff_to_labels": float(np.max(np.abs(ev.e_r - labels_e_r))),
            "frac_posthoc_accepted": float(np.mean(ev.accepted))}
