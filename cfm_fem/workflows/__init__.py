"""Workflows the command line and `cfm_fem.api` expose, one orchestration per command, called
by both: `sweep.run` (``sweep``), `design_run` (``design``), `kinematics` (``kinematics``),
`tolerance` (``tolerance``), `coupled_run` (``coupled``), `quality` (``quality``), `fig4_run`
(``fig4``), `compare_run` (``compare``), `diagnose.run` (``diagnose``); `inputs` takes a bench,
recording or map as an object or a file the same way for all. The numerics behind them: the
sweep (`sweep`), the coupled Monte Carlo (`coupled`), recordings against the simulation
(`compare`), paper Fig. 4 (`fig4`), synthetic recordings (`synthetic`) and the diagnosis
(`diagnose`).
"""
