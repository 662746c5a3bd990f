"""The ART ablation table of docs/art_training.md, rendered from `evaluate --suite rollouts`
outputs (benchmarks/results/art_ablation/*.json).

    python benchmarks/analyses/ablation_table.py          # print the table (markdown)
    python benchmarks/analyses/ablation_table.py --check  # exit 1 if docs/art_training.md differs

Each row is one model on the held-out scenarios of its JSON: the rollout metrics (median and
q90 of 100 E_R, the share with C(t_1) = 0, the share inside the post hoc region) beside the
model's teacher-forced validation loss and training length, read from the checkpoint's
provenance that `evaluate` copied into the JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results" / "art_ablation"
DOC = ROOT / "docs" / "art_training.md"
BEGIN, END = "<!-- ablation-table:begin -->", "<!-- ablation-table:end -->"

# row order and what each run varies (file stem -> label)
ROWS = {
    "fresh7_previous_default": "previous shipped default (18 k, 5 epochs, CPU)",
    "A_small_feat": "A small, per-feature (reference)",
    "B_small_step": "B small, per-time-step normalisation",
    "C_small_gate": "C small, burn gate",
    "D_small_step_gate": "D small, per-time-step + burn gate",
    "E_medium_feat": "E medium (2.7 M), per-feature",
    "F_small_5k": "F small, 5,000 trajectories",
    "G_small_10k": "G small, 10,000 trajectories",
    "H_small_bf16": "H small, bf16 (same wall time as A)",
    "R_small_rtn": "R small, RTN",
    "K_small_gate_roe": "K small, burn gate, converged (shipped ROE)",
    "K_small_gate_rtn": "K small RTN, burn gate, converged (shipped RTN)",
    "L_small_gate_w1_roe": "L as K, gate weight 1.0",
    "M_medium_gate_roe": "M medium, burn gate, converged",
    "N_dagger_gate_roe": "N as K + 3,000 DAgger rows of K",
    "fresh7_K_small_gate_roe": "K (shipped ROE), fresh seed 7",
    "fresh7_K_small_gate_rtn": "K RTN (shipped RTN), fresh seed 7",
    "fresh7_C_small_gate": "C, fresh seed 7",
    "fresh7_N_dagger_gate_roe": "N, fresh seed 7",
    "fresh7_O_dagger_ft_roe": "O K fine-tuned on 2.7 k fresh + 2.7 k DAgger rows of K (cost "
                              "ratio <= 1.5), fresh seed 7",
    "fresh7_sweep_roe": "K + conditioning sweep (in flight, ROE), fresh seed 7",
    "fresh8_sweep_roe": "K + conditioning sweep (in flight, ROE), fresh seed 8",
    "fresh7_O_dagger_ft_sweep_roe": "O + conditioning sweep (in flight), fresh seed 7",
    "fresh7_sweep_rtn": "K RTN + conditioning sweep (in flight), fresh seed 7",
    "fresh8_sweep_rtn": "K RTN + conditioning sweep (in flight), fresh seed 8",
    "det7_previous_det_roe": "deterministic: previous ROE (no gate, 5 epochs, CPU), fresh seed 7",
    "det7_previous_det_rtn": "deterministic: previous RTN (no gate, 5 epochs, CPU), fresh seed 7",
    "det7_gate_det_roe": "deterministic: ROE, burn gate, 10 k, 7 epochs, CPU (shipped before)",
    "det7_gate_det_rtn": "deterministic: RTN, burn gate, 10 k, 7 epochs, CPU (shipped before)",
    "det7_gpu10k_e18_det_roe": "deterministic: ROE, burn gate, 10 k, 18 epochs, GPU",
    "det7_gpu10k_e18_det_rtn": "deterministic: RTN, burn gate, 10 k, 18 epochs, GPU",
    "det7_gpu10k_e30_det_roe": "deterministic: ROE, burn gate, 10 k, 30 epochs, GPU",
    "det7_gpu10k_e30_det_rtn": "deterministic: RTN, burn gate, 10 k, 30 epochs, GPU",
    "det7_gpu25k_e18_det_roe": "deterministic: ROE, burn gate, 25 k, 18 epochs, GPU",
    "det7_gpu25k_e18_det_rtn": "deterministic: RTN, burn gate, 25 k, 18 epochs, GPU",
    "det7_gpu25k_e30_det_roe": "deterministic: ROE, burn gate, 25 k, 30 epochs, GPU (shipped)",
    "det7_gpu25k_e30_det_rtn": "deterministic: RTN, burn gate, 25 k, 30 epochs, GPU (shipped)",
}

# the oracle rows (the plans' own controls through the same machinery), from these JSONs
ORACLES = {"A_small_feat": "oracle: the plans' own controls",
           "det7_gate_det_roe": "oracle, deterministic: the plans' own controls"}


def _held(model: dict, n: int) -> str:
    """"N fresh" (a dataset no model was trained on, --split all) or "N test"."""
    return f"{n} {'fresh' if model.get('split') == 'all' else 'test'}"


def _models(results: Path, labels: dict[str, str]):
    """(label, the JSON's model entry) for each stem of `labels` whose JSON exists."""
    for stem, label in labels.items():
        path = results / f"{stem}.json"
        if path.is_file():
            yield label, json.loads(path.read_text())["models"][0]


def _row(label: str, m: dict) -> str:
    t = m.get("training") or {}
    cfg = t.get("config") or {}
    tc = t.get("train_config") or {}
    held = _held(m, m["n_scenarios"])
    epochs = f"{t['epoch']:.1f}" if t.get("epoch") is not None else "-"
    val = f"{t['best_val_loss']:.3f}" if t.get("best_val_loss") is not None else "-"
    n_train = t.get("n_train") or "-"
    params = f"{t['n_parameters'] / 1e6:.2f}" if t.get("n_parameters") else "-"
    norm = cfg.get("normalization", "feature")
    gate = "yes" if cfg.get("burn_gate") else "no"
    return (f"| {label} | {held} | {m['e_r_pct_median']:.2f} | {m['e_r_pct_q90']:.1f} | "
            f"{100 * m['frac_c_art_zero']:.1f} | {100 * m['frac_posthoc_accepted']:.1f} | "
            f"{val} | {n_train} | {epochs} | {params} | {norm} | {gate} | "
            f"{tc.get('precision', 'fp32')} |")


def render(results: Path = RESULTS) -> str:
    """The markdown table, one row per JSON in ROWS order (missing files are skipped)."""
    head = ("| run | held-out scenarios | 100 E_R median [%] | 100 E_R q90 [%] | E_C = 0 [%] | "
            "post hoc [%] | val. loss | train traj. | epochs | M params | normalisation | "
            "gate | precision |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    lines += [_row(label, model) for label, model in _models(results, ROWS)]
    for label, model in _models(results, ORACLES):
        oracle = model["oracle"]
        lines.append(
            f"| {label} | {_held(model, oracle['n_scenarios'])} | "
            f"{oracle['e_r_pct_median']:.2f} | {oracle['e_r_pct_q90']:.1f} | "
            f"{100 * oracle['frac_c_zero']:.1f} | {100 * oracle['frac_posthoc_accepted']:.1f} | "
            "- | - | - | - | - | - | - |")
    return "\n".join(lines) + "\n"


def in_doc(doc: Path = DOC) -> str:
    """The table currently between the markers of the documentation page."""
    text = doc.read_text()
    return text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare with docs/art_training.md")
    args = p.parse_args(argv)
    table = render()
    if args.check:
        ok = in_doc() == table
        print("docs/art_training.md is current" if ok else "docs/art_training.md is stale")
        return 0 if ok else 1
    print(table, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
