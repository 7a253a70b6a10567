"""The README's commands and example stay true."""

import re
import shutil
from pathlib import Path

import pytest

from helpers import benchmark_script, run_as_script

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _bash_commands():
    blocks = re.findall(r"```bash\n(.*?)```", README, flags=re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def test_ci_runs_the_readme_test_command():
    test_commands = [c for c in _bash_commands() if "pytest" in c]
    assert len(test_commands) == 1, test_commands
    assert test_commands[0] in (ROOT / ".ci" / "run").read_text()


@pytest.mark.end_to_end
def test_readme_example_runs():
    code = "\n".join(re.findall(r"```python\n(.*?)```", README, flags=re.S))
    code += "\nassert traj.ys.fiber.shape == (51, 3)\nassert traj.result == pk.RESULTS.successful\n"
    code += "assert sol.ys.fiber.shape == (7, 3)\nassert out.fiber.shape == (8, 101, 3)\n"
    run_as_script(code, "README.md")


TABLE_WRITER = ROOT / "benchmarks" / "write_tables.py"
"""Writes tables from the results; it measures nothing (no --quick)."""
BENCHMARK_SCRIPTS = [s for s in sorted((ROOT / "benchmarks").glob("*.py")) if not s.name.startswith("_") and s != TABLE_WRITER]


def test_benchmark_scripts_are_there():
    assert len(BENCHMARK_SCRIPTS) >= 5, BENCHMARK_SCRIPTS


@pytest.mark.end_to_end
@pytest.mark.parametrize("script", BENCHMARK_SCRIPTS, ids=lambda s: s.stem)
def test_benchmark_script_runs_quick(script, tmp_path):
    """`python benchmarks/<script>.py --quick --out DIR`, its command line
    called in this process: it writes its results there."""
    assert benchmark_script(script).main(["--quick", "--out", str(tmp_path)]) == tmp_path
    assert list(tmp_path.glob("*.json"))


def test_generated_tables_agree_with_the_results_and_an_edit_is_found(tmp_path):
    """benchmarks/README.md, docs/concepts/choosing.md and notebook 05 hold
    the tables that the benchmark scripts make from benchmarks/results;
    --check fails where a generated block was edited by hand, and a rewrite
    restores it (in a copy of the documents and results)."""
    write_tables = benchmark_script(TABLE_WRITER)
    assert write_tables.main(["--check"]) == 0
    shutil.copytree(ROOT / "benchmarks" / "results", tmp_path / "benchmarks" / "results")
    for document in [*write_tables.DOCUMENTS, write_tables.NOTEBOOK]:  # a copy: the writer may write
        (tmp_path / document).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / document).write_text((ROOT / document).read_text())
    page = tmp_path / "docs" / "concepts" / "choosing.md"
    page.write_text(page.read_text().replace("| free body | 1 |", "| free body | 1 (edited) |", 1))
    assert write_tables.main(["--check"], root=tmp_path) == 1
    assert write_tables.main([], root=tmp_path) == 0
    assert page.read_text() == (ROOT / "docs" / "concepts" / "choosing.md").read_text()
