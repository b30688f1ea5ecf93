"""Homogeneous parts of a node's field polynomial at many displacements (vectorised).

Written by ``scripts/generate_harmonic_parts.py`` from the monomial order of
`cfm_fem.models.harmonic_basis`; edit the script, not this file.

For a node's expanded model (`expand_node`, monomial coefficients of degree <= 5, zero
beyond the node's own degree) and scaled displacements u, part q (q = 1 .. 5) of component c
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
N_SLOTS = 15


@nb.njit(**FJIT)
def homogeneous_parts(cexp, u, t0, m, parts):
    """Parts 1 .. 5 of the field change at the scaled displacements ``u[:, t0:t0 + m]``.

    Parameters
    ----------
    cexp : ndarray, shape (3, 56), T
        Monomial coefficients per component (`expand_node`), zero beyond the node's degree.
    u : ndarray, shape (3, >= t0 + m)
        Scaled displacements.
    t0, m : int
        First trial and number of trials, m <= `PART_BLOCK`.
    parts : ndarray, shape (>= N_SLOTS * PART_PITCH,), T
        Output, see the module docstring.
    """
    k0_1 = cexp[0, 1]
    k0_2 = cexp[0, 2]
    k0_3 = cexp[0, 3]
    k0_4 = cexp[0, 4]
    k0_5 = cexp[0, 5]
    k0_6 = cexp[0, 6]
    k0_7 = cexp[0, 7]
    k0_8 = cexp[0, 8]
    k0_9 = cexp[0, 9]
    k0_10 = cexp[0, 10]
    k0_11 = cexp[0, 11]
    k0_12 = cexp[0, 12]
    k0_13 = cexp[0, 13]
    k0_14 = cexp[0, 14]
    k0_15 = cexp[0, 15]
    k0_16 = cexp[0, 16]
    k0_17 = cexp[0, 17]
    k0_18 = cexp[0, 18]
    k0_19 = cexp[0, 19]
    k0_20 = cexp[0, 20]
    k0_21 = cexp[0, 21]
    k0_22 = cexp[0, 22]
    k0_23 = cexp[0, 23]
    k0_24 = cexp[0, 24]
    k0_25 = cexp[0, 25]
    k0_26 = cexp[0, 26]
    k0_27 = cexp[0, 27]
    k0_28 = cexp[0, 28]
    k0_29 = cexp[0, 29]
    k0_30 = cexp[0, 30]
    k0_31 = cexp[0, 31]
    k0_32 = cexp[0, 32]
    k0_33 = cexp[0, 33]
    k0_34 = cexp[0, 34]
    k0_35 = cexp[0, 35]
    k0_36 = cexp[0, 36]
    k0_37 = cexp[0, 37]
    k0_38 = cexp[0, 38]
    k0_39 = cexp[0, 39]
    k0_40 = cexp[0, 40]
    k0_41 = cexp[0, 41]
    k0_42 = cexp[0, 42]
    k0_43 = cexp[0, 43]
    k0_44 = cexp[0, 44]
    k0_45 = cexp[0, 45]
    k0_46 = cexp[0, 46]
    k0_47 = cexp[0, 47]
    k0_48 = cexp[0, 48]
    k0_49 = cexp[0, 49]
    k0_50 = cexp[0, 50]
    k0_51 = cexp[0, 51]
    k0_52 = cexp[0, 52]
    k0_53 = cexp[0, 53]
    k0_54 = cexp[0, 54]
    k0_55 = cexp[0, 55]
    k1_1 = cexp[1, 1]
    k1_2 = cexp[1, 2]
    k1_3 = cexp[1, 3]
    k1_4 = cexp[1, 4]
    k1_5 = cexp[1, 5]
    k1_6 = cexp[1, 6]
    k1_7 = cexp[1, 7]
    k1_8 = cexp[1, 8]
    k1_9 = cexp[1, 9]
    k1_10 = cexp[1, 10]
    k1_11 = cexp[1, 11]
    k1_12 = cexp[1, 12]
    k1_13 = cexp[1, 13]
    k1_14 = cexp[1, 14]
    k1_15 = cexp[1, 15]
    k1_16 = cexp[1, 16]
    k1_17 = cexp[1, 17]
    k1_18 = cexp[1, 18]
    k1_19 = cexp[1, 19]
    k1_20 = cexp[1, 20]
    k1_21 = cexp[1, 21]
    k1_22 = cexp[1, 22]
    k1_23 = cexp[1, 23]
    k1_24 = cexp[1, 24]
    k1_25 = cexp[1, 25]
    k1_26 = cexp[1, 26]
    k1_27 = cexp[1, 27]
    k1_28 = cexp[1, 28]
    k1_29 = cexp[1, 29]
    k1_30 = cexp[1, 30]
    k1_31 = cexp[1, 31]
    k1_32 = cexp[1, 32]
    k1_33 = cexp[1, 33]
    k1_34 = cexp[1, 34]
    k1_35 = cexp[1, 35]
    k1_36 = cexp[1, 36]
    k1_37 = cexp[1, 37]
    k1_38 = cexp[1, 38]
    k1_39 = cexp[1, 39]
    k1_40 = cexp[1, 40]
    k1_41 = cexp[1, 41]
    k1_42 = cexp[1, 42]
    k1_43 = cexp[1, 43]
    k1_44 = cexp[1, 44]
    k1_45 = cexp[1, 45]
    k1_46 = cexp[1, 46]
    k1_47 = cexp[1, 47]
    k1_48 = cexp[1, 48]
    k1_49 = cexp[1, 49]
    k1_50 = cexp[1, 50]
    k1_51 = cexp[1, 51]
    k1_52 = cexp[1, 52]
    k1_53 = cexp[1, 53]
    k1_54 = cexp[1, 54]
    k1_55 = cexp[1, 55]
    k2_1 = cexp[2, 1]
    k2_2 = cexp[2, 2]
    k2_3 = cexp[2, 3]
    k2_4 = cexp[2, 4]
    k2_5 = cexp[2, 5]
    k2_6 = cexp[2, 6]
    k2_7 = cexp[2, 7]
    k2_8 = cexp[2, 8]
    k2_9 = cexp[2, 9]
    k2_10 = cexp[2, 10]
    k2_11 = cexp[2, 11]
    k2_12 = cexp[2, 12]
    k2_13 = cexp[2, 13]
    k2_14 = cexp[2, 14]
    k2_15 = cexp[2, 15]
    k2_16 = cexp[2, 16]
    k2_17 = cexp[2, 17]
    k2_18 = cexp[2, 18]
    k2_19 = cexp[2, 19]
    k2_20 = cexp[2, 20]
    k2_21 = cexp[2, 21]
    k2_22 = cexp[2, 22]
    k2_23 = cexp[2, 23]
    k2_24 = cexp[2, 24]
    k2_25 = cexp[2, 25]
    k2_26 = cexp[2, 26]
    k2_27 = cexp[2, 27]
    k2_28 = cexp[2, 28]
    k2_29 = cexp[2, 29]
    k2_30 = cexp[2, 30]
    k2_31 = cexp[2, 31]
    k2_32 = cexp[2, 32]
    k2_33 = cexp[2, 33]
    k2_34 = cexp[2, 34]
    k2_35 = cexp[2, 35]
    k2_36 = cexp[2, 36]
    k2_37 = cexp[2, 37]
    k2_38 = cexp[2, 38]
    k2_39 = cexp[2, 39]
    k2_40 = cexp[2, 40]
    k2_41 = cexp[2, 41]
    k2_42 = cexp[2, 42]
    k2_43 = cexp[2, 43]
    k2_44 = cexp[2, 44]
    k2_45 = cexp[2, 45]
    k2_46 = cexp[2, 46]
    k2_47 = cexp[2, 47]
    k2_48 = cexp[2, 48]
    k2_49 = cexp[2, 49]
    k2_50 = cexp[2, 50]
    k2_51 = cexp[2, 51]
    k2_52 = cexp[2, 52]
    k2_53 = cexp[2, 53]
    k2_54 = cexp[2, 54]
    k2_55 = cexp[2, 55]
    for t in range(m):
        x = u[0, t0 + t]
        y = u[1, t0 + t]
        z = u[2, t0 + t]
        x2 = x * x
        x3 = x2 * x
        x4 = x3 * x
        x5 = x4 * x
        y2 = y * y
        y3 = y2 * y
        y4 = y3 * y
        y5 = y4 * y
        z2 = z * z
        z3 = z2 * z
        z4 = z3 * z
        z5 = z4 * z
        parts[0 * PART_PITCH + t] = k0_1 * x + k0_2 * y + k0_3 * z
        parts[1 * PART_PITCH + t] = k1_1 * x + k1_2 * y + k1_3 * z
        parts[2 * PART_PITCH + t] = k2_1 * x + k2_2 * y + k2_3 * z
        v5 = x * y
        v6 = x * z
        v8 = y * z
        parts[3 * PART_PITCH + t] = (
            k0_4 * x2 + k0_5 * v5 + k0_6 * v6 + k0_7 * y2 + k0_8 * v8 + k0_9 * z2
        )
        parts[4 * PART_PITCH + t] = (
            k1_4 * x2 + k1_5 * v5 + k1_6 * v6 + k1_7 * y2 + k1_8 * v8 + k1_9 * z2
        )
        parts[5 * PART_PITCH + t] = (
            k2_4 * x2 + k2_5 * v5 + k2_6 * v6 + k2_7 * y2 + k2_8 * v8 + k2_9 * z2
        )
        v11 = x2 * y
        v12 = x2 * z
        v13 = x * y2
        v14 = x * y * z
        v15 = x * z2
        v17 = y2 * z
        v18 = y * z2
        parts[6 * PART_PITCH + t] = (
            k0_10 * x3
            + k0_11 * v11
            + k0_12 * v12
            + k0_13 * v13
            + k0_14 * v14
            + k0_15 * v15
            + k0_16 * y3
            + k0_17 * v17
            + k0_18 * v18
            + k0_19 * z3
        )
        parts[7 * PART_PITCH + t] = (
            k1_10 * x3
            + k1_11 * v11
            + k1_12 * v12
            + k1_13 * v13
            + k1_14 * v14
            + k1_15 * v15
            + k1_16 * y3
            + k1_17 * v17
            + k1_18 * v18
            + k1_19 * z3
        )
        parts[8 * PART_PITCH + t] = (
            k2_10 * x3
            + k2_11 * v11
            + k2_12 * v12
            + k2_13 * v13
            + k2_14 * v14
            + k2_15 * v15
            + k2_16 * y3
            + k2_17 * v17
            + k2_18 * v18
            + k2_19 * z3
        )
        v21 = x3 * y
        v22 = x3 * z
        v23 = x2 * y2
        v24 = x2 * y * z
        v25 = x2 * z2
        v26 = x * y3
        v27 = x * y2 * z
        v28 = x * y * z2
        v29 = x * z3
        v31 = y3 * z
        v32 = y2 * z2
        v33 = y * z3
        parts[9 * PART_PITCH + t] = (
            k0_20 * x4
            + k0_21 * v21
            + k0_22 * v22
            + k0_23 * v23
            + k0_24 * v24
            + k0_25 * v25
            + k0_26 * v26
            + k0_27 * v27
            + k0_28 * v28
            + k0_29 * v29
            + k0_30 * y4
            + k0_31 * v31
            + k0_32 * v32
            + k0_33 * v33
            + k0_34 * z4
        )
        parts[10 * PART_PITCH + t] = (
            k1_20 * x4
            + k1_21 * v21
            + k1_22 * v22
            + k1_23 * v23
            + k1_24 * v24
            + k1_25 * v25
            + k1_26 * v26
            + k1_27 * v27
            + k1_28 * v28
            + k1_29 * v29
            + k1_30 * y4
            + k1_31 * v31
            + k1_32 * v32
            + k1_33 * v33
            + k1_34 * z4
        )
        parts[11 * PART_PITCH + t] = (
            k2_20 * x4
            + k2_21 * v21
            + k2_22 * v22
            + k2_23 * v23
            + k2_24 * v24
            + k2_25 * v25
            + k2_26 * v26
            + k2_27 * v27
            + k2_28 * v28
            + k2_29 * v29
            + k2_30 * y4
            + k2_31 * v31
            + k2_32 * v32
            + k2_33 * v33
            + k2_34 * z4
        )
        v36 = x4 * y
        v37 = x4 * z
        v38 = x3 * y2
        v39 = x3 * y * z
        v40 = x3 * z2
        v41 = x2 * y3
        v42 = x2 * y2 * z
        v43 = x2 * y * z2
        v44 = x2 * z3
        v45 = x * y4
        v46 = x * y3 * z
        v47 = x * y2 * z2
        v48 = x * y * z3
        v49 = x * z4
        v51 = y4 * z
        v52 = y3 * z2
        v53 = y2 * z3
        v54 = y * z4
        parts[12 * PART_PITCH + t] = (
            k0_35 * x5
            + k0_36 * v36
            + k0_37 * v37
            + k0_38 * v38
            + k0_39 * v39
            + k0_40 * v40
            + k0_41 * v41
            + k0_42 * v42
            + k0_43 * v43
            + k0_44 * v44
            + k0_45 * v45
            + k0_46 * v46
            + k0_47 * v47
            + k0_48 * v48
            + k0_49 * v49
            + k0_50 * y5
            + k0_51 * v51
            + k0_52 * v52
            + k0_53 * v53
            + k0_54 * v54
            + k0_55 * z5
        )
        parts[13 * PART_PITCH + t] = (
            k1_35 * x5
            + k1_36 * v36
            + k1_37 * v37
            + k1_38 * v38
            + k1_39 * v39
            + k1_40 * v40
            + k1_41 * v41
            + k1_42 * v42
            + k1_43 * v43
            + k1_44 * v44
            + k1_45 * v45
            + k1_46 * v46
            + k1_47 * v47
            + k1_48 * v48
            + k1_49 * v49
            + k1_50 * y5
            + k1_51 * v51
            + k1_52 * v52
            + k1_53 * v53
            + k1_54 * v54
            + k1_55 * z5
        )
        parts[14 * PART_PITCH + t] = (
            k2_35 * x5
            + k2_36 * v36
            + k2_37 * v37
            + k2_38 * v38
            + k2_39 * v39
            + k2_40 * v40
            + k2_41 * v41
            + k2_42 * v42
            + k2_43 * v43
            + k2_44 * v44
            + k2_45 * v45
            + k2_46 * v46
            + k2_47 * v47
            + k2_48 * v48
            + k2_49 * v49
            + k2_50 * y5
            + k2_51 * v51
            + k2_52 * v52
            + k2_53 * v53
            + k2_54 * v54
            + k2_55 * z5
        )
