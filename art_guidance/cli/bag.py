"""`art-guidance bag reindex DIR`: make a crashed recording readable by rosbag2 readers again."""
from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    """Check every MCAP file of a bag folder (each chunk's CRC, also in files that have a
    summary) and rebuild every file that is torn, damaged or has no summary from its intact
    chunks (a torn end after a crash is dropped, damaged chunks are named and dropped), then
    rewrite metadata.yaml to what is on disk, noting the repair in its custom_data. What was
    kept and what could not be recovered (file, chunk, byte offset, messages lost per the
    file's message index and the old metadata.yaml) is printed."""
    from art_guidance.record.reindex import repair_bag

    repair = repair_bag(args.dir)
    print(f"{len(repair.rewritten)} file(s) rewritten in {args.dir}")
    return 3 if repair.data_lost else 0


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
    reindex = actions.add_parser("reindex", help="check and rebuild torn, damaged or "
                                 "unsummarised files and metadata.yaml",
                                 description=run.__doc__ + " Exit codes: 0 nothing lost "
                                 "(files rebuilt or not; damage that cost no message, such as "
                                 "a summary that fails its CRC and is not needed or a damaged "
                                 "copy of a chunk read intact, is named and dropped); 2 bad "
                                 "input, or a running recorder still writes to the folder "
                                 "(refused, nothing touched); 3 data was lost (damaged chunks "
                                 "whose messages were read nowhere else, or fewer messages on "
                                 "disk than the old metadata.yaml counted); the folder is "
                                 "repaired all the same.")
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
