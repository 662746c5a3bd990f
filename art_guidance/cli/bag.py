"""`art-guidance bag reindex DIR`: make a crashed recording readable by rosbag2 readers again."""
from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    """Rebuild every MCAP file of a bag folder that has no summary (a torn end after a crash
    is dropped, complete chunks are kept) and rewrite metadata.yaml; every change is printed."""
    from art_guidance.record.reindex import reindex_bag

    rewritten = reindex_bag(args.dir)
    print(f"{rewritten} file(s) rewritten in {args.dir}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("bag", help="maintain a recorded bag folder (reindex after a crash)",
                       description="Maintain a bag folder written by the guidance node.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    reindex = actions.add_parser("reindex", help="rebuild files without summary and "
                                 "metadata.yaml", description=run.__doc__ + " Refuses a "
                                 "folder a running recorder still writes to (exit 2).")
    reindex.add_argument("dir", help="the bag folder (metadata.yaml and <name>_<k>.mcap)")
    reindex.set_defaults(func=run)
