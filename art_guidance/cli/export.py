"""`art-guidance export`: a checkpoint as one ONNX file that flies without torch."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from art_guidance.extras import EXPORT


def run(args: argparse.Namespace) -> int:
    """Export a trained checkpoint's decoding step, with its configuration, normalisation,
    provenance and the source checkpoint's sha256, to one ONNX file (written whole: a crash
    leaves no partial file), then load it back on ONNX Runtime and check it against the
    checkpoint (weights checksum and a probe torch computed)."""
    from art_guidance.art.checkpoint import load
    from art_guidance.art.onnx_art import exported_path, load_exported
    from art_guidance.art.onnx_export import export
    from art_guidance.art.provider import pinned_sha256

    model = Path(args.model)
    art = load(model, expected_sha256=pinned_sha256(model))
    out = Path(args.out) if args.out else exported_path(model)
    sha = export(art, out, force=args.force)
    check = load_exported(out, expected_checkpoint_sha256=art.sha256)
    print(json.dumps({"out": str(out), "sha256": sha, "bytes": out.stat().st_size,
                      "checkpoint": model.name, "checkpoint_sha256": art.sha256,
                      "n_parameters": check.n_parameters}))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("export", help="export a checkpoint to ONNX (the torch-free runtime)",
                       description=run.__doc__ + " Fly it with `--art-runtime onnx` (plan) or "
                       "the node parameter `art_runtime`. Exit 0 written and checked, 2 bad "
                       "input (an existing file without --force, a corrupt checkpoint).")
    p.add_argument("model", help="checkpoint (.pt) written by `art-guidance train`")
    p.add_argument("--out", default=None, help="the ONNX file to write (default: beside the "
                   "checkpoint, same name with .onnx: where `art_runtime` auto and onnx look)")
    p.add_argument("--force", action="store_true", help="replace an existing file")
    p.set_defaults(func=run, needs=EXPORT)
