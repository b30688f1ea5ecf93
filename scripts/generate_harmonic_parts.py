"""Write `cfm_fem/_kernels/harmonic_parts.py`: the degree-5 field polynomial, unrolled.

The sweep evaluates every node's harmonic model (`cfm_fem.models.harmonic`) at all its trial
displacements. Written as one straight-line body per trial, storing the homogeneous parts in one
flat block array whose row pitch is a compile-time constant, the loop over trials is one that
LLVM vectorises: the stores provably do not overlap, so no run-time alias checks are needed.
This script writes that body from the monomial order of `cfm_fem.models.harmonic_basis`;
`tests/test_harmonic_parts.py` checks that the module in the package is its output.

Usage: ``python scripts/generate_harmonic_parts.py [--check]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cfm_fem.models.harmonic_basis import MAX_DEGREE, monomial_exponents  # noqa: E402

LINE_LENGTH = 100
TARGET = ROOT / "cfm_fem" / "_kernels" / "harmonic_parts.py"

HEADER = '''"""Homogeneous parts of a node's field polynomial at many displacements (vectorised).

Written by ``scripts/generate_harmonic_parts.py`` from the monomial order of
`cfm_fem.models.harmonic_basis`; edit the script, not this file.

For a node's expanded model (`expand_node`, monomial coefficients of degree <= {deg}, zero
beyond the node's own degree) and scaled displacements u, part q (q = 1 .. {deg}) of component c
is the sum of the degree-q monomials of u times their coefficients, so that

    B(s u) - B(0) = sum_q s^q part_q.

Trials are taken in blocks of at most `PART_BLOCK`; part q of component c of trial t of a block is
``parts[(3 (q - 1) + c) * PART_PITCH + t]``. A straight-line body per trial and a constant row pitch
are what let LLVM vectorise the loop over trials.
"""

from __future__ import annotations

import numba as nb

from .options import FJIT

#: Trials per block.
PART_BLOCK = 512

#: Row pitch of the part arrays: one cache line more than a block, so that the rows of a trial,
#: read and written together, do not all fall into the same cache set (as a pitch of 4 KiB
#: would have them).
PART_PITCH = PART_BLOCK + 8

#: Part rows: 3 components per degree.
N_SLOTS = {n_slots}


@nb.njit(**FJIT)
def homogeneous_parts(cexp, u, t0, m, parts):
    """Parts 1 .. {deg} of the field change at the scaled displacements ``u[:, t0:t0 + m]``.

    Parameters
    ----------
    cexp : ndarray, shape (3, {n_mono}), T
        Monomial coefficients per component (`expand_node`), zero beyond the node's degree.
    u : ndarray, shape (3, >= t0 + m)
        Scaled displacements.
    t0, m : int
        First trial and number of trials, m <= `PART_BLOCK`.
    parts : ndarray, shape (>= N_SLOTS * PART_PITCH,), T
        Output, see the module docstring.
    """
'''


def _power(a: str, k: int) -> str:
    return "" if k == 0 else a if k == 1 else f"{a}{k}"


def generate() -> str:
    """Source of the module."""
    exps = monomial_exponents(MAX_DEGREE)
    n_mono = len(exps)
    header = HEADER.format(deg=MAX_DEGREE, n_mono=n_mono, n_slots=3 * MAX_DEGREE)
    lines = [header.rstrip("\n")]
    for c in range(3):
        for m in range(1, n_mono):
            lines.append(f"    k{c}_{m} = cexp[{c}, {m}]")
    lines.append("    for t in range(m):")
    lines += [f"        {a} = u[{i}, t0 + t]" for i, a in enumerate("xyz")]
    for a in "xyz":
        for k in range(2, MAX_DEGREE + 1):
            lines.append(f"        {a}{k} = {_power(a, k - 1)} * {a}")
    slot = 0
    m = 1
    for q in range(1, MAX_DEGREE + 1):
        mons = []
        while m < n_mono and exps[m].sum() == q:
            factors = [_power(a, int(k)) for a, k in zip("xyz", exps[m], strict=True)]
            factors = [f for f in factors if f]
            if len(factors) > 1:
                lines.append(f"        v{m} = {' * '.join(factors)}")
                mons.append((m, f"v{m}"))
            else:
                mons.append((m, factors[0]))
            m += 1
        for c in range(3):
            terms = [f"k{c}_{mm} * {v}" for mm, v in mons]
            target = f"parts[{slot} * PART_PITCH + t]"
            line = f"        {target} = {' + '.join(terms)}"
            inner = f"            {' + '.join(terms)}"
            if len(line) <= LINE_LENGTH:
                lines.append(line)
            elif len(inner) <= LINE_LENGTH:  # the layouts `ruff format` gives a long sum
                lines += [f"        {target} = (", inner, "        )"]
            else:
                lines.append(f"        {target} = (")
                lines += [f"            {'+ ' if j else ''}{term}" for j, term in enumerate(terms)]
                lines.append("        )")
            slot += 1
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the module is not current")
    args = ap.parse_args(argv)
    src = generate()
    if args.check:
        current = TARGET.read_text() if TARGET.exists() else ""
        print("current" if current == src else f"{TARGET} differs from the generator's output")
        return 0 if current == src else 1
    TARGET.write_text(src)
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
