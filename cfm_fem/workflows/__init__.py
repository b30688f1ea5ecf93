"""Workflows the command line exposes: the sweep (`sweep`), the coupled Monte Carlo
(`coupled`), recordings against the simulation (`compare`), paper Fig. 4 (`fig4`), synthetic
recordings (`synthetic`) and the diagnosis (`diagnose`).
"""
