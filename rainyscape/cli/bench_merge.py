"""rs-bench-merge: several rs-bench results files as one set of tables.

Usage:
  rs-bench-merge RESULTS.json [RESULTS.json ...] [out=TABLES.md] [name=NAME] [force=true]

A scene set's rows are often trained apart: the plain field and its clean-view ceiling in one
rs-bench, each rain method in another, a slow scene on its own. rs-bench-merge reads their
OUT/NAME.json files and prints rs-bench's tables over all their finished cells, so that the
per-set averages and the gain over the plain field out of the gap rain leaves (the share a
rain method closes) are computed over every scene and method together. A cell held by two
files is kept once if both trained the same config, and refused otherwise (exit 2, naming
both). A scene's gain-over-gap needs its ceiling cell (the plain field on the clean views)
in one of the files. out= also writes the tables to a new file; an existing one is refused unless
force=true. Nothing is trained.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from rainyscape.cli import run_cli
from rainyscape.cli.args import Command, opt, parse, print_help
from rainyscape.errors import ConfigError, DataError


@dataclass
class MergeArgs:
    out: str = opt("", "also write the tables to this new Markdown file")
    name: str = opt("merged", "the tables' title")
    force: bool = opt(False, "write out= over an existing file")


COMMAND = Command("rs-bench-merge", __doc__, MergeArgs, positional="RESULTS.json files")


def main(argv: list[str]) -> int:
    args = parse(argv, COMMAND)
    if args.help:
        return print_help(COMMAND)
    if not args.positional:
        raise ConfigError("rs-bench-merge: name at least one results file (OUT/NAME.json of an rs-bench); "
                          "see rs-bench-merge --help")
    from rainyscape.comparison.merge import merge_results
    from rainyscape.comparison.results import read_results
    from rainyscape.comparison.tables import markdown_report
    from rainyscape.formats.atomic import write_text_atomic
    from rainyscape.formats.output import check_can_create

    opts = args.options
    out = Path(opts.out).expanduser() if opts.out else None
    if out is not None:
        if out.suffix != ".md":
            raise ConfigError(f"out={out}: the tables are Markdown: name a .md file")
        if out.exists() and not opts.force:
            raise DataError(f"out={out}: the file exists; pass force=true to replace it")
        check_can_create(out.parent, "out")
    paths = [Path(p).expanduser() for p in args.positional]
    cells, results = merge_results([(p, read_results(p)) for p in paths])
    if not cells:
        raise DataError(f"{', '.join(map(str, paths))}: no finished cell to tabulate")
    results["name"] = opts.name
    tables = markdown_report(cells, results)
    print(tables)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out, tables)
        print(f"tables: {out}", file=sys.stderr)
    return 0


def entry() -> None:
    sys.exit(run_cli(main))


if __name__ == "__main__":
    entry()
