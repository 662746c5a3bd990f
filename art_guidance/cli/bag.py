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


def render(args: argparse.Namespace) -> int:
    """Draw what the Foxglove layout (config/foxglove_layout.json) shows from a recorded bag:
    the plan, ellipsoids, drift arcs coloured by margin, burns and the navigated deputy in the
    RT plane, the margin and delta-v plots and the status text (the node records its
    visualisation topics with every solve)."""
    from art_guidance.record.render import render_bag

    counts = render_bag(args.dir, args.png, args.plan)
    print(f"{args.png}: plan {args.plan} of {counts['plans']}, {counts['drift']} drift arcs, "
          f"{counts['burns']} burns, {counts['deputy_fixes']} deputy fixes")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("bag", help="maintain or draw a recorded bag folder (reindex after a "
                       "crash, render its visualisation topics)",
                       description="Maintain or draw a bag folder written by the guidance node.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    reindex = actions.add_parser("reindex", help="rebuild files without summary and "
                                 "metadata.yaml", description=run.__doc__ + " Refuses a "
                                 "folder a running recorder still writes to (exit 2).")
    reindex.add_argument("dir", help="the bag folder (metadata.yaml and <name>_<k>.mcap)")
    reindex.set_defaults(func=run)
    draw = actions.add_parser("render", help="draw the bag's visualisation topics to a PNG",
                              description=render.__doc__ + " Example: art-guidance bag render "
                              "out/demo/run_*/mcap --png out/bag.png")
    draw.add_argument("dir", help="the bag folder or an MCAP file")
    draw.add_argument("--png", default="out/bag.png", help="output PNG (default out/bag.png)")
    draw.add_argument("--plan", type=int, default=-1,
                      help="which plan put in force to draw (0 = first, -1 = last)")
    draw.set_defaults(func=render)
