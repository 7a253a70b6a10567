"""Coefficients of symmetric composition methods Ψ_h = Φ_{γ_m h} ∘ … ∘ Φ_{γ₁ h}.

Composing a symmetric one-step method Φ of even order p with step fractions
γ₁, …, γ_m raises its order when the γ satisfy the composition order
conditions (Hairer, Lubich & Wanner, *Geometric Numerical Integration*, 2nd
ed., Springer 2006, §II.4 and §V.3). A set validates itself: Σγ = 1, the
palindrome γ_k = γ_{m+1−k} (which makes Ψ symmetric), and Σγ^q = 0 for the
odd q with p < q < order (the conditions for the error terms h^q of the base
that are not brackets of lower ones; necessary, not sufficient: the orders
are confirmed empirically in the tests, on Lie-group problems and on a
Strang splitting of non-commuting matrices).

`triple_jump(p)` and `suzuki_fractal(p)` exist for any even base order p;
the other sets are for a symmetric base of order 2.
"""

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class CompositionCoefficients:
    """Step fractions of a symmetric composition method.

    `fractions` are γ₁…γ_m (a palindrome), `order` the order of the
    composition when the base is symmetric of order `base_order`, `source`
    where the numbers come from.
    """

    name: str
    fractions: tuple
    order: int
    base_order: int
    source: str
    tolerance: float = 1e-14

    def __post_init__(self):
        fractions = tuple(float(g) for g in self.fractions)
        object.__setattr__(self, "fractions", fractions)
        gamma = np.array(fractions)
        if gamma.ndim != 1 or gamma.size < 1:
            raise ValueError(f"{self.name}: fractions must be a non-empty sequence of numbers.")
        for field in ("order", "base_order"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{self.name}: {field} must be a positive int, got {value!r}.")
        if self.base_order % 2 or self.order % 2:
            raise ValueError(f"{self.name}: symmetric methods have even order; got base order {self.base_order}, order {self.order}.")
        if abs(gamma.sum() - 1) > self.tolerance:
            raise ValueError(f"{self.name}: the fractions sum to {gamma.sum()!r}, not 1.")
        if not np.allclose(gamma, gamma[::-1], rtol=0, atol=self.tolerance):
            raise ValueError(f"{self.name}: the fractions are not a palindrome, so the composition is not symmetric.")
        for q in range(self.base_order + 1, self.order, 2):
            moment = float(np.sum(gamma**q))
            if abs(moment) > self.tolerance * max(1.0, float(np.sum(np.abs(gamma) ** q))):
                raise ValueError(f"{self.name}: Σγ^{q} = {moment:.3e}, not 0, so the order cannot exceed {q - 1}.")

    @property
    def num_steps(self) -> int:
        return len(self.fractions)


def triple_jump(base_order: int = 2) -> CompositionCoefficients:
    """γ₁ = γ₃ = 1/(2 − 2^{1/(p+1)}), γ₂ = 1 − 2γ₁: order p + 2 from a
    symmetric base of order p (Yoshida 1990, Phys. Lett. A 150, 262–268;
    Suzuki 1990; Creutz & Gocksch 1989)."""
    g = 1.0 / (2.0 - 2.0 ** (1.0 / (base_order + 1)))
    return CompositionCoefficients(
        f"triple jump (order {base_order + 2})",
        (g, 1.0 - 2.0 * g, g),
        base_order + 2,
        base_order,
        "H. Yoshida, Construction of higher order symplectic integrators, Phys. Lett. A 150 (1990) 262-268.",
    )


def suzuki_fractal(base_order: int = 2) -> CompositionCoefficients:
    """γ₁ = γ₂ = γ₄ = γ₅ = 1/(4 − 4^{1/(p+1)}), γ₃ = 1 − 4γ₁: order p + 2 from
    a symmetric base of order p with smaller fractions (and smaller error
    constants) than the triple jump (Suzuki 1990, Phys. Lett. A 146, 319–323)."""
    g = 1.0 / (4.0 - 4.0 ** (1.0 / (base_order + 1)))
    return CompositionCoefficients(
        f"Suzuki's fractal (order {base_order + 2})",
        (g, g, 1.0 - 4.0 * g, g, g),
        base_order + 2,
        base_order,
        "M. Suzuki, Fractal decomposition of exponential operators, Phys. Lett. A 146 (1990) 319-323.",
    )


def _palindrome(half):
    return tuple(half) + tuple(reversed(half[:-1]))


yoshida_triple_jump = triple_jump(2)
"""Order 4 in 3 steps of a symmetric order-2 base."""

suzuki_5 = suzuki_fractal(2)
"""Order 4 in 5 steps of a symmetric order-2 base."""

kahan_li_6 = CompositionCoefficients(
    "Kahan-Li s9odr6a (order 6)",
    _palindrome(
        [
            0.39216144400731413927925056,
            0.33259913678935943859974864,
            -0.70624617255763935980996482,
            0.08221359629355080023149045,
            0.79854399093482996339895035,
        ]
    ),
    order=6,
    base_order=2,
    source="W. Kahan, R.-C. Li, Composition constants for raising the orders of unconventional schemes for "
    "ordinary differential equations, Math. Comp. 66 (1997) 1089-1099; as printed in Hairer, Lubich & Wanner, "
    "Geometric Numerical Integration (2006), §V.3.2.",
)
"""Order 6 in 9 steps of a symmetric order-2 base."""

mclachlan_8 = CompositionCoefficients(
    "McLachlan s15odr8 (order 8)",
    _palindrome(
        [
            0.74167036435061295344822780,
            -0.40910082580003159399730010,
            0.19075471029623837995387626,
            -0.57386247111608226665638773,
            0.29906418130365592384446354,
            0.33462491824529818378495798,
            0.31529309239676659663205666,
            -0.79688793935291635401978884,
        ]
    ),
    order=8,
    base_order=2,
    source="R. I. McLachlan, On the numerical integration of ordinary differential equations by symmetric "
    "composition methods, SIAM J. Sci. Comput. 16 (1995) 151-168; as printed in Hairer, Lubich & Wanner (2006), "
    "§V.3.2.",
)
"""Order 8 in 15 steps of a symmetric order-2 base."""

kahan_li_8 = CompositionCoefficients(
    "Kahan-Li s17odr8a (order 8)",
    _palindrome(
        [
            0.13020248308889008087881763,
            0.56116298177510838456196441,
            -0.38947496264484728640807860,
            0.15884190655515560089621075,
            -0.39590389413323757733623154,
            0.18453964097831570709183254,
            0.25837438768632204729397911,
            0.29501172360931029887096624,
            -0.60550853383003451169892108,
        ]
    ),
    order=8,
    base_order=2,
    source="W. Kahan, R.-C. Li, Math. Comp. 66 (1997) 1089-1099; as printed in Hairer, Lubich & Wanner (2006), §V.3.2.",
)
"""Order 8 in 17 steps of a symmetric order-2 base (smaller error constant
than `mclachlan_8` per step, at two more steps)."""

ALL_COMPOSITIONS = (yoshida_triple_jump, suzuki_5, kahan_li_6, mclachlan_8, kahan_li_8)
