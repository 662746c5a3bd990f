"""What a DAgger directory is made from and how it is identified: the fields it stores, the
scenario pool of the source dataset SRC and SRC's configuration, the check that the model was
trained on data of SRC's kind, the manifest header and the check that refuses to resume a
directory made with another model, SRC or batch (see `data.dagger` for the sample rule).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from art_guidance import __version__
from art_guidance.config import MODES, GuidanceConfig
from art_guidance.data import stages as _stages
from art_guidance.data.dagger_worker import DAGGER_STREAM, DaggerSpec
from art_guidance.data.stages import STAGES, GenerationSpec
from art_guidance.data.storage import complete_shards
from art_guidance.errors import ConfigError, InputError

SEED_RULE = ("scenario of sample i: pool[i mod P], pool = SRC's feasible train-split samples "
             "with a CVX solution, by index; node k_i = 1 + default_rng(SeedSequence([seed, "
             f"{DAGGER_STREAM:#x}, i])).integers(N - 3)")
FORMAT = 1

# Stored per sample; the generator's FIELDS with these meanings, plus train_from and src_index.
FIELDS = dict(_stages.FIELDS)
FIELDS.update({
    "index": "() int64, DAgger sample index i in 0..n-1",
    "seed": "() int64, scenario seed of the SRC sample (SRC's seed rule)",
    "kept_stage": "() int8, stage of the expert's re-solve from node train_from: 3 passive "
                  "safety, 2 collision avoidance, 0 none feasible",
    "roe_m": "(N, 6) pre-burn a-scaled ROE [m]: the rollout's before train_from, the expert's "
             "from it",
    "dv_rtn_mps": "(N, 3) impulsive delta-v in RTN [m/s]: the rollout's before train_from, "
                  "the expert's from it",
    "constraint_to_go": "(N,) int32, C(t_i) of the stitched row under the mode's full-horizon "
                        "passive-safety model",
    "margin_m": "(N,) passive-safety margin of the stitched row under the mode's full-horizon "
                "model [m], >= 0 safe",
    "cvx_roe_m": "(N, 6) CVX (stage 1) pre-burn ROE of the SRC scenario [m]",
    "cvx_dv_rtn_mps": "(N, 3) CVX delta-v of the SRC scenario in RTN [m/s]",
    "cvx_cost_mps": "() CVX cost of the SRC scenario, the rollout's -R(t_1) [m/s]",
    "cvx_constraint_to_go0": "() int32, C_CVX(t_1) of the SRC scenario",
    "stage_status": "(3,) int8, ScpStatus value per stage of the re-solve (cvx, ca, ps)",
    "stage_iterations": "(3,) int32, convex subproblems solved per stage of the re-solve",
    "stage_cost_mps": "(3,) cost of each re-solve stage over nodes train_from..N-1 [m/s]",
    "stage_time_ms": "(3,) wall time per re-solve stage [ms] (not reproducible)",
    "train_from": "() int64, k in 1..N-3: first node whose control is an expert label (the "
                  "nodes before it are context only)",
    "src_index": "() int64, sample index of the scenario in SRC",
})
SCENARIO_FIELDS = ("seed", "waypoint", "rtn0", "target_rtn", "roe0_m", "roe_f_m", "cvx_roe_m",
                   "cvx_dv_rtn_mps", "cvx_cost_mps", "cvx_constraint_to_go0")


def scenario_pool(src: str | Path, n: int) -> dict[str, np.ndarray]:
    """The first min(n, P) scenarios of SRC's pool (feasible, train split, CVX solved), read
    shard by shard (only their SCENARIO_FIELDS are kept), in sample-index order.

    Returns:
        {"src_index": (P',), SCENARIO_FIELDS...} and "pool_size": () P.

    Raises:
        DatasetError: an incomplete or corrupt SRC.
        InputError: SRC has no usable scenario.
    """
    parts = []
    for a in complete_shards(src):
        cost = a["cvx_cost_mps"]
        keep = (a["feasible"] & ~a["is_test"] & (a["cvx_constraint_to_go0"] >= 0)
                & np.isfinite(cost) & (np.nan_to_num(cost) > 0))
        parts.append({"src_index": a["index"][keep],
                      **{k: a[k][keep] for k in SCENARIO_FIELDS}})
    pool = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    size = int(pool["src_index"].size) if pool else 0
    if size == 0:
        raise InputError("--data", "holds no feasible train-split scenario with a CVX solution",
                         str(src))
    used = np.argsort(pool["src_index"], kind="stable")[:min(int(n), size)]
    return dict({k: v[used] for k, v in pool.items()}, pool_size=np.int64(size))


def check_model(art: object, generation: GenerationSpec, model: str) -> None:
    """Refuse a model trained on data of another mode or configuration than SRC's."""
    from art_guidance.art.rollout import training_config

    data = art.meta.get("dataset", {}) if isinstance(art.meta, dict) else {}
    config = training_config(art)
    if config is None or data.get("mode") not in MODES:
        raise InputError("--model", "records no training data mode and configuration; "
                         "DAgger needs a model trained with `art-guidance train`", model)
    trained = GenerationSpec.build(data["mode"], 0, config).config_sha256
    # the same rule as `train --init`: the planning choices only flight uses may differ (a
    # model's bundle written before such an option existed records none of it)
    diff = config.data_differences(generation.config)
    if data["mode"] != generation.mode or diff:
        raise InputError("--model", f"was trained on {data['mode']} data of config "
                         f"{trained[:12]}; --data is {generation.mode} data of config "
                         f"{generation.config_sha256[:12]} (differing: "
                         f"{', '.join(diff) or 'mode'}): roll out a model of SRC's kind",
                         model)
    if art.config.context < generation.scenario.n_nodes:
        raise InputError("--model", f"context K = {art.config.context} is shorter than the "
                         f"{generation.scenario.n_nodes}-node horizon", model)


def source_generation(src: str | Path, header: dict) -> GenerationSpec:
    """SRC's mode and configuration, checked against what this code would generate."""
    if "dagger" in header:
        raise InputError("--data", "is a DAgger dataset; pass the dataset its scenarios come "
                         f"from ({header['dagger'].get('src_dir')})", str(src))
    bundle = header.get("config", {}).get("guidance_config")
    if bundle is None or header.get("mode") not in MODES:
        raise InputError("--data", "is not a dataset of `art-guidance generate` (no mode or "
                         "configuration bundle in its header)", str(src))
    spec = GenerationSpec.build(header["mode"], 0, GuidanceConfig.from_json(bundle))
    if spec.scenario.n_nodes < 4:
        raise InputError("--data", "needs a horizon of at least 4 nodes (takeover nodes "
                         "1..N-3)", spec.scenario.n_nodes)
    if spec.config_sha256 != header.get("config_sha256"):
        raise ConfigError(f"{src}: its configuration fingerprint "
                          f"{str(header.get('config_sha256'))[:12]} differs from this code's "
                          f"{spec.config_sha256[:12]} for the same configuration (another "
                          "pipeline version): the expert would label with another pipeline; "
                          "regenerate SRC")
    return spec


def manifest_header(spec: DaggerSpec, src: str | Path, src_header: dict, src_digest: str,
                    pool_size: int) -> dict:
    """Manifest header of the DAgger directory (resume keys: see `check_resume`)."""
    return {"mode": src_header["mode"], "base_seed": spec.seed, "n": spec.n,
            "seed_rule": SEED_RULE, "config_sha256": src_header["config_sha256"],
            "config": src_header["config"], "stages": list(STAGES), "fields": FIELDS,
            "test_fraction": 0.0,
            "dagger": {"format": FORMAT, "model_sha256": spec.model_sha256,
                       "model_path": str(spec.model_path), "src_dir": str(src),
                       "src_manifest_sha256": src_digest, "seed": spec.seed,
                       "rollout_batch": spec.batch, "pool_size": int(pool_size)},
            "art_guidance_version": __version__,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


_DAGGER_KEYS = (("model_sha256", "--model"), ("src_manifest_sha256", "--data"),
                ("rollout_batch", "--batch"), ("format", "--out"))


def check_resume(root: Path, stored: dict, wanted: dict) -> None:
    """Refuse to resume a directory made with another model, SRC or batch."""
    have = stored.get("dagger")
    if not isinstance(have, dict):
        raise InputError("--out", "holds a dataset that is not a DAgger dataset; use a new "
                         "--out", str(root))
    for key, option in _DAGGER_KEYS:
        if have.get(key) != wanted["dagger"][key]:
            raise InputError(option, f"the directory holds DAgger data with {key} = "
                             f"{have.get(key)!r}; this run asks for "
                             f"{wanted['dagger'][key]!r}. Re-run with the same options or use "
                             "a new --out")
