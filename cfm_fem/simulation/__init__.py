"""An independent bench-and-probe simulator to test `cfm-fem diagnose` against.

Nothing here shares model code with the tool: its own HTM chain of the reference bench with
Table II draws (:mod:`.bench`), an exact 3-D field from a magpylib permanent-magnet quadrupole
(:mod:`.magnet`), scan plans with their timing and approach directions (:mod:`.scan`), tracker and
Hall recordings with concealed effects (:mod:`.tracker`, :mod:`.hall`), and the files a user
would give the diagnosis (:mod:`.output`, :mod:`.cases`). Concealed effects and their truth use the
diagnosis' parameter names and units.

A randomized family (:mod:`.family`) draws a whole configuration from a seed: magnets of every
order and a solenoid (:mod:`.magnets`), benches stacked in any order (:mod:`.benches`), grids,
on-the-fly lines, circles and sparse maps (:mod:`.scans`), noise levels, references, and nulls or
one effect sized to a stated joint significance against its neighbours (:mod:`.significance`).

Example
-------
>>> from cfm_fem.simulation import write_case                          # doctest: +SKIP
>>> files = write_case("reversal", seed=3, folder="sim", size="small")  # doctest: +SKIP
>>> files["args"]  # then: cfm-fem diagnose *args --out DIR            # doctest: +SKIP
"""

from .cases import CASES, write_case
from .family import draw_config, write_family_case

__all__ = ["CASES", "write_case", "draw_config", "write_family_case"]
