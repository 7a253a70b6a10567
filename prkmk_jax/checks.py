"""Run-time checks of data, applied together at the start of a run.

`checked(x, failed, message)` is `eqx.error_if(x, failed, message)`: it
returns x, and raises `message` where `failed` holds (eagerly, or when the
compiled program runs). Inside `collected_checks()` it records the check
instead, and the collector applies every recorded check at once with one
`eqx.branched_error_if`, raising the message of the first check that fails.
Each `error_if` is a conditional branch of its own in the compiled program;
the start of a run checks the state, dt and the scene's parameters, and a
run of a few trajectories would pay for each branch
(`benchmarks/against_revision.py` measures single-trajectory runs).
"""

import contextlib
import contextvars
from collections.abc import Iterator
from typing import TypeVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool

Checked = TypeVar("Checked")


class CollectedChecks:
    """The checks recorded inside one `collected_checks()` block."""

    def __init__(self):
        self.failed: list[Bool[Array, ""]] = []
        self.messages: list[str] = []

    def record(self, failed: Bool[ArrayLike, "..."], message: str) -> None:
        self.failed.append(jnp.any(failed))
        self.messages.append(message)

    def applied_to(self, x: Checked) -> Checked:
        """`x`, raising the message of the first recorded check that fails."""
        if not self.failed:
            return x
        failed = jnp.stack(self.failed)
        return eqx.branched_error_if(x, jnp.any(failed), jnp.argmax(failed), self.messages)


_COLLECTOR: contextvars.ContextVar[CollectedChecks | None] = contextvars.ContextVar("prkmk_jax_collected_checks", default=None)


def checked(x: Checked, failed: Bool[ArrayLike, "..."], message: str) -> Checked:
    """`eqx.error_if(x, failed, message)`, or, inside `collected_checks()`,
    `x` with the check recorded for the collector to apply."""
    collector = _COLLECTOR.get()
    if collector is None:
        return eqx.error_if(x, failed, message)
    collector.record(failed, message)
    return x


@contextlib.contextmanager
def collected_checks() -> Iterator[CollectedChecks]:
    """Record the `checked` calls made inside the block; apply them after it
    with `CollectedChecks.applied_to`, to values that every later
    computation depends on (the checks act only through its return value)."""
    collector = CollectedChecks()
    token = _COLLECTOR.set(collector)
    try:
        yield collector
    finally:
        _COLLECTOR.reset(token)
