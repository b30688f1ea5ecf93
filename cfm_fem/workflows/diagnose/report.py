"""The readable report of a diagnosis, as the diagnosis package names it: `markdown` and
`figures` of `cfm_fem.report.diagnosis_figures`."""

from ...report.diagnosis_figures import figures, markdown

__all__ = ["markdown", "figures"]
