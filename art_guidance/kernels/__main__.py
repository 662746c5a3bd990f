"""`python -m art_guidance.kernels`: compile the kernels into their cache (or load them from
it) and say where; exit 0 when the compiled path is ready, 1 when the numpy path is taken.

The node and the one-shot commands start it in the background on a cold cache; a flight image
runs it once at build time, so that no flight computer ever compiles (`art-guidance kernels`
is the same step with the command-line's help)."""
from __future__ import annotations

import argparse
import sys

from art_guidance import kernels


def main(argv: list[str] | None = None) -> int:
    """Fill the cache (or, with --status, only say what is there); returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m art_guidance.kernels",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--status", action="store_true",
                        help="say where the cache is and whether it holds the kernels; compile "
                        "nothing")
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    args = parser.parse_args(argv)
    if args.status:
        text = kernels.cache_status()
    else:
        text = kernels.prepare("compiled", wait=True)
    if not args.quiet:
        print(text)
    return 0 if args.status or kernels.ready_s() is not None else 1


if __name__ == "__main__":
    sys.exit(main())
