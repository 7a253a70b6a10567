"""Writes the benchmarks' tables into the documents that quote them.

Each script in `SCRIPTS` makes its own tables from its own results files:
`tables(results) -> {name: markdown}`, `results` the folder they are in. A
document holds a table between the lines

    <!-- write_tables.py: NAME -->
    <!-- /write_tables.py -->

and this script rewrites what is between them; nothing there is edited by
hand. Notebook 05 shows the decision table as the output of the cell that
calls `accuracy.decision_table`, which this script writes too. `--check`
writes nothing and exits with status 1 where a document differs from what
the results give (the test suite runs it).

    python benchmarks/write_tables.py            # after a benchmark run
    python benchmarks/write_tables.py --check
"""

import argparse
import importlib
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout whose documents and `benchmarks/results` this script reads and writes."""
SCRIPTS = ("accuracy", "long_time", "round_off", "stability", "throughput", "gradients", "ensembles")
DOCUMENTS = ("benchmarks/README.md", "docs/concepts/choosing.md", "docs/concepts/models.md")
NOTEBOOK = "notebooks/05_choosing_a_method.ipynb"
BLOCK = re.compile(r"(<!-- write_tables\.py: (\w+) -->\n)(?:.*?\n)??(<!-- /write_tables\.py -->)", re.S)
"""`??`: an empty block matches as empty, not as everything up to a later block's end."""


def all_tables(root: Path) -> dict[str, str]:
    sys.path.insert(0, str(Path(__file__).parent))
    tables = {}
    for name in SCRIPTS:
        tables.update(importlib.import_module(name).tables(root / "benchmarks" / "results"))
    return tables


def rewritten(text: str, tables: dict[str, str], where: str) -> str:
    def table(match):
        if match.group(2) not in tables:
            raise ValueError(f"{where}: no benchmark makes a table named {match.group(2)!r}")
        return match.group(1) + tables[match.group(2)] + "\n" + match.group(3)

    return BLOCK.sub(table, text)


def notebook_with_table(path: Path, table: str) -> tuple[str, str]:
    """(the notebook's text, the text with the output of its decision-table
    cell set to `table`), both as nbformat writes them."""
    import nbformat

    text = path.read_text()
    nb = nbformat.reads(text, as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code" and "accuracy.decision_table" in c.source]
    if len(cells) != 1:
        raise ValueError(f"{path.name}: expected one code cell showing accuracy.decision_table, found {len(cells)}")
    markdown = {"text/markdown": table, "text/plain": "<IPython.core.display.Markdown object>"}
    cells[0].outputs = [nbformat.v4.new_output("display_data", data=markdown, metadata={})]
    return nbformat.writes(nbformat.reads(text, as_version=4)) + "\n", nbformat.writes(nb) + "\n"


def main(argv=None, root: Path = ROOT) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 where a document differs from the results")
    args = parser.parse_args(argv)
    tables = all_tables(root)
    changed = {}
    for document in DOCUMENTS:
        text = (root / document).read_text()
        new = rewritten(text, tables, document)
        changed[document] = new if new != text else None
    before, after = notebook_with_table(root / NOTEBOOK, tables["decision"])
    changed[NOTEBOOK] = after if after != before else None
    stale = [document for document, text in changed.items() if text is not None]
    if args.check:
        if stale:
            print("generated tables out of date in: " + ", ".join(stale) + " (run python benchmarks/write_tables.py)")
        return 1 if stale else 0
    for document in stale:
        (root / document).write_text(changed[document])
    print("written: " + (", ".join(stale) or "nothing (all up to date)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
