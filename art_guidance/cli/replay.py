"""`art-guidance replay`: re-solve a recorded log and compare."""
from __future__ import annotations

import argparse
from art_guidance.files import write_json_atomic


def run(args: argparse.Namespace) -> int:
    """Re-solve every request recorded in an MCAP log (file or bag folder) and compare plans."""
    from art_guidance.record.replay import OTHER_MODEL, replay

    # --numerics (given before the command) replays every solve on that path; else each solve
    # replays on the path it ran on
    report = replay(args.log, args.model, args.allow_uncompared, args.numerics)
    print(f"model: {report['model']}")
    if report["config_check"] != "ok":
        print(f"CONFIGURATION: {report['config_check']}")
    for problem in report["metadata_problems"]:
        print(f"METADATA: {problem}")
    if report["metadata_check"].startswith("unsealed"):
        print(f"note: metadata {report['metadata_check']}")
    if args.json:
        write_json_atomic(args.json, report)
    for row in report["per_solve"]:
        verdict = {True: "match", False: "MISMATCH", None: "skipped"}[row["match"]]
        if row.get("reason") == OTHER_MODEL:
            verdict = "UNCOMPARED"
        extra = (f"cost diff {row['cost_rel_diff']:.1e}, dv diff {row['dv_max_abs_diff_mps']:.1e}"
                 if row["match"] is not None else row.get("reason", ""))
        if row.get("replayed_warm_start"):
            extra += f", warm start {row['replayed_warm_start']}"
            if "rollout_max_abs_diff_mps" in row:
                extra += f", rollout diff {row['rollout_max_abs_diff_mps']:.1e}"
        print(f"{row['plan_id']:>12} {row['status']:<15} {verdict:<8} {extra}")
    skipped = "".join(f", {report[k]} {what}" for k, what in (
        ("uncompared", "UNCOMPARED (another model)"), ("deadline_hit", "hit their deadline"))
        if report[k])
    print(f"{report['matched']}/{report['compared']} matched "
          f"({report['solves']} solves{skipped}, {len(report['truncated'])} truncated file(s), "
          f"{len(report['damaged'])} damaged stretch(es))")
    _print_losses(report)
    return int(report["exit_code"])


def _print_losses(report: dict) -> None:
    """What could not be read or was lost, and what to do about it."""
    from art_guidance.record.loss import describe

    for torn in report["truncated"]:
        print(f"torn: {torn}")
    for d in report["damaged"]:
        where = f"chunk {d['chunk']}" if d["chunk"] is not None else "data"
        held = ("" if d["messages"] is None or not d["lost_data"] else
                f"; {d['messages']} message(s) lost")
        label = "DAMAGED" if d["lost_data"] else f"damaged, nothing lost ({d['no_loss']})"
        print(f"{label}: {d['file']} {where} at byte offset {d['offset']} "
              f"({d['length']} bytes skipped): {d['reason']}{held}")
    for kind, ids in report["unmatched"].items():
        if ids:
            print(f"unmatched: {len(ids)} {kind.replace('_', ' ')}: {', '.join(ids)}")
    print(describe(report["lost"]))
    if report["lost"]["source"] != "metadata.yaml" or "retention" in report["lost"]["metadata"]:
        print(f"note: {report['lost']['metadata']}")
    for note in report["lost"]["notes"] + report["notes"]:
        print(f"note: {note}")
    for line in report["advice"]:
        print(f"advice: {line}")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("replay", help="re-solve a recorded MCAP log and compare",
                       description=run.__doc__ + " Every chunk's CRC is checked: a damaged "
                       "chunk is named (file, chunk, byte offset, what failed) and skipped, the "
                       "intact chunks after it are read; a torn end (a crash inside a write) "
                       "keeps the complete chunks before it. What was read is compared with "
                       "metadata.yaml and the lost messages and solves are reported per type, "
                       "as are solve records without their plan. Every run metadata value "
                       "(configuration, model and runtime checksums, parameters, versions) is "
                       "checked against its seal, before any is used; a log from before the "
                       "seal is said to be unsealed, and a seal under an altered key, or missing "
                       "where the file's header says its writer seals, is an alteration. A log "
                       "recorded with another model than the one replayed is reported as such "
                       "and its ART solves are not compared; solves that hit their deadline "
                       "cannot be reproduced and are not compared either. Each solve is "
                       "replayed on the numerics path it ran on (numpy while the kernels "
                       "compiled on a cold cache, else compiled; `art-guidance --numerics "
                       "numpy replay` replays all on one path). Exit codes: 0 every "
                       "compared solve matches (cost to 1e-6 relative, delta-v to 1e-5 m/s; "
                       "where ART proposed: its rollout to 1e-6 m/s, the same post hoc decision "
                       "and warm start) and nothing was lost; 1 a compared solve does not "
                       "match, or the configuration or a run metadata value was altered after "
                       "recording, whatever it has become; 2 bad input (no such log, no "
                       "configuration in it, a value that does not read in a log from before "
                       "the seal); 3 every compared solve matches but data was lost; 4 no "
                       "compared solve differs but solves were not compared because they were "
                       "recorded with another model (see --allow-uncompared). Damage that cost "
                       "no message (a summary not needed, a damaged copy of a chunk read "
                       "intact) is named but is no loss.")
    p.add_argument("log", help="an .mcap file or a bag folder of them")
    p.add_argument("--model", default=None,
                   help="ART checkpoint to replay learned warm starts with (default: the "
                   "shipped model, if it is the recorded one)")
    p.add_argument("--json", default=None, help="also write the report as JSON")
    p.add_argument("--allow-uncompared", action="store_true",
                   help="do not exit 4 when solves recorded with another model than the one "
                   "replayed are left uncompared (they are still listed)")
    p.set_defaults(func=run)
