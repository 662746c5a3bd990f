"""`art-guidance replay`: re-solve a recorded log and compare."""
from __future__ import annotations

import argparse
from art_guidance.files import write_json_atomic


def run(args: argparse.Namespace) -> int:
    """Re-solve every request recorded in an MCAP log (file or bag folder) and compare plans."""
    from art_guidance.record.replay import replay

    report = replay(args.log, args.model)
    print(f"model: {report['model']}")
    if args.json:
        write_json_atomic(args.json, report)
    for row in report["per_solve"]:
        verdict = {True: "match", False: "MISMATCH", None: "skipped"}[row["match"]]
        extra = (f"cost diff {row['cost_rel_diff']:.1e}, dv diff {row['dv_max_abs_diff_mps']:.1e}"
                 if row["match"] is not None else row.get("reason", ""))
        if row.get("replayed_warm_start"):
            extra += f", warm start {row['replayed_warm_start']}"
            if "rollout_max_abs_diff_mps" in row:
                extra += f", rollout diff {row['rollout_max_abs_diff_mps']:.1e}"
        print(f"{row['plan_id']:>12} {row['status']:<15} {verdict:<8} {extra}")
    print(f"{report['matched']}/{report['compared']} matched "
          f"({report['solves']} solves, {len(report['truncated'])} truncated file(s))")
    if report["truncated"]:  # read as it is; other readers need the files repaired
        print(f"a file ends torn (crash during a write): `art-guidance bag reindex {args.log}` "
              "makes the folder readable by rosbag2 and rosbags")
    return 0 if report["mismatched"] == 0 else 1


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("replay", help="re-solve a recorded MCAP log and compare",
                       description=run.__doc__ + " Exit 0 when every compared solve "
                       "matches (cost to 1e-6 relative, delta-v to 1e-5 m/s; where ART "
                       "proposed: its rollout to 1e-6 m/s, the same post hoc decision and "
                       "warm start), 1 otherwise. A log recorded with another model than the "
                       "one given is reported as such and its ART solves are skipped.")
    p.add_argument("log", help="an .mcap file or a bag folder of them")
    p.add_argument("--model", default=None,
                   help="ART checkpoint to replay learned warm starts with (default: the "
                   "shipped model, if it is the recorded one)")
    p.add_argument("--json", default=None, help="also write the report as JSON")
    p.set_defaults(func=run)
