"""Turn coverage's JSON report into the per-package table of docs/reliability.md ("Coverage").

    python .ci/coverage_table.py build/coverage/coverage.json docs/reliability.md

One row per subpackage of art_guidance (its modules at every depth), one for the package's own
top-level modules and a total: statements, line coverage (statements run), branches and branch
coverage (branch destinations taken), as `coverage report` counts them. The table replaces what
lies between the two marker comments of the page; with `-` as the page it is printed instead.
Exit 2 when the report is not a branch-coverage report of art_guidance or a marker is missing.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

PACKAGE = "art_guidance"
TOP_LEVEL = "(top-level modules)"
TABLE_BEGIN = "<!-- coverage table start -->"
TABLE_END = "<!-- coverage table end -->"
COUNTS = ("num_statements", "covered_lines", "num_branches", "covered_branches")


def package_counts(report: dict) -> dict[str, dict[str, int]]:
    """Subpackage -> summed counts of its files (TOP_LEVEL for art_guidance/*.py)."""
    rows: dict[str, dict[str, int]] = defaultdict(lambda: dict.fromkeys(COUNTS, 0))
    for name, entry in report["files"].items():
        parts = Path(name).parts
        if PACKAGE not in parts:
            raise ValueError(f"{name} is not a module of {PACKAGE}")
        inside = parts[len(parts) - parts[::-1].index(PACKAGE):]
        row = rows[inside[0] if len(inside) > 1 else TOP_LEVEL]
        for key in COUNTS:
            row[key] += entry["summary"][key]
    return dict(rows)


def _percent(covered: int, total: int) -> str:
    return f"{100.0 * covered / total:.1f}" if total else "-"


def render(rows: dict[str, dict[str, int]]) -> str:
    """The markdown table: subpackages by name, the top-level modules, then the total."""
    names = sorted(n for n in rows if n != TOP_LEVEL) + ([TOP_LEVEL] if TOP_LEVEL in rows else [])
    total = {key: sum(r[key] for r in rows.values()) for key in COUNTS}
    lines = ["| package | statements | line coverage % | branches | branch coverage % |",
             "|---|---:|---:|---:|---:|"]
    for name, row in [*((n, rows[n]) for n in names), ("**total**", total)]:
        label = name if name.startswith(("(", "*")) else f"`{name}`"
        lines.append(f"| {label} | {row['num_statements']:,} "
                     f"| {_percent(row['covered_lines'], row['num_statements'])} "
                     f"| {row['num_branches']:,} "
                     f"| {_percent(row['covered_branches'], row['num_branches'])} |")
    return "\n".join(lines)


def replace_table(page: str, table: str) -> str:
    """`page` with the text between the two markers replaced by `table`."""
    start, end = page.find(TABLE_BEGIN), page.find(TABLE_END)
    if start < 0 or end < start:
        raise ValueError(f"the page has no {TABLE_BEGIN} ... {TABLE_END} markers")
    return f"{page[:start + len(TABLE_BEGIN)]}\n{table}\n{page[end:]}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="coverage's JSON report (`coverage json`)")
    parser.add_argument("page", help="the markdown page to update, or - to print the table")
    args = parser.parse_args(argv)
    report = json.loads(args.report.read_text())
    try:
        if not report.get("meta", {}).get("branch_coverage"):
            raise ValueError(f"{args.report} has no branch coverage (coverage run --branch)")
        table = render(package_counts(report))
        if args.page == "-":
            print(table)
            return 0
        page = Path(args.page)
        page.write_text(replace_table(page.read_text(), table))
    except ValueError as exc:
        print(f"coverage_table: {exc}", file=sys.stderr)
        return 2
    print(f"coverage_table: {len(report['files'])} files -> {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
