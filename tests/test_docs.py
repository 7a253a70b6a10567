"""The documentation site stays true: every public name has a reference
entry, and the pages' examples run (at a small size where a page says n),
in this process as a script would."""

import inspect
import re
from pathlib import Path

import pytest

import prkmk_jax as pk
from helpers import run_as_script

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _reference_entries() -> set[str]:
    """Dotted names that `::: name` lines or their `members:` lists document."""
    entries = set()
    for page in (DOCS / "api").glob("*.md"):
        current = None
        for line in page.read_text().splitlines():
            directive = re.match(r"::: ([\w.]+)", line)
            if directive:
                current = directive.group(1)
                entries.add(current)
                continue
            member = re.match(r"\s+- (\w+)$", line)
            if member and current is not None:
                entries.add(f"{current}.{member.group(1)}")
    return entries


MODULES = [pk, pk.elliptic, pk.coordinates, pk.groups, pk.scenes, pk.diagnostics, pk.methods, pk.stage_plan, pk.tableaus, pk.compositions]


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__)
def test_every_public_name_is_in_the_reference(module):
    entries = _reference_entries()
    documented_objects = set()
    for entry in entries:
        obj = pk
        for part in entry.split(".")[1:]:
            obj = getattr(obj, part)
        documented_objects.add(id(obj))
    missing = []
    for name, value in vars(module).items():
        if name.startswith("_") or inspect.ismodule(value):
            continue
        own = getattr(value, "__module__", None)
        if own is not None and not own.startswith("prkmk_jax"):
            continue  # re-exported from jax, typing, …
        if f"{module.__name__}.{name}" not in entries and id(value) not in documented_objects:
            missing.append(name)
    assert not missing, f"{module.__name__}: no reference entry for {missing}"


def _python_blocks(page: Path) -> str:
    return "\n".join(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))


# What each page says its example gives, checked after it runs.
PAGES = {
    "getting-started.md": [
        "assert jnp.abs(jnp.swapaxes(q, -1, -2) @ q - jnp.eye(3)).max() < 1e-13",
        "assert jnp.ptp(0.5 * jnp.sum(pi * pi / inertia, axis=-1)) < 1e-11",
    ],
    "batch-and-fit.md": [
        "assert ys.fiber.shape == (n, 11, 3)",
        "assert float(jnp.max(invariants['orthogonality'])) < 1e-13",
        "assert float(jnp.max(jnp.abs(fit.value - truth.lever))) < 1e-8",
        "assert float(value) > 0 and gradient.shape == (3,)",
    ],
    "concepts/diffrax.md": ["assert sol.ys.fiber.shape == (7, 3)"],
    "concepts/batches.md": ["assert ys.fiber.shape == (n, 11, 3)"],
    "concepts/many-machines.md": [
        "assert isinstance(mine.fiber, np.ndarray) and mine.fiber.shape == (n, 3)",
        "assert float(worst) == np.max(np.abs(mine.fiber)) and gradient.shape == (3,)",
    ],
    "concepts/tableaus.md": ["assert order8.order == 8 and order4.order == 4"],
}


@pytest.mark.end_to_end
@pytest.mark.parametrize("page", list(PAGES))
def test_page_examples_run(page):
    code = _python_blocks(DOCS / page)
    assert code, page
    # The pages' batch size n is for a reader's machine; the test runs a few.
    code = re.sub(r"^n = \d+", "n = 8", code, flags=re.M)
    code += "\n" + "\n".join(PAGES[page]) + "\n"
    run_as_script(code, str(DOCS / page))
