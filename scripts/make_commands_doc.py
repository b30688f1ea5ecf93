"""Write docs/commands.md: every cfm-fem command with its ``--help`` text, taken from the parser.

    python scripts/make_commands_doc.py            # rewrite docs/commands.md
    python scripts/make_commands_doc.py --check    # exit 1 if docs/commands.md is out of date

The list of commands and their option lists are the parser's own (every subcommand of
`cfm_fem.cli.build_parser`, in its order; the help formatted at 100 columns), so the page cannot
drift from the command line. The example and the short text above each list are kept here, in
`EXAMPLES`; a command without an entry there fails the script (and `--check`), naming it.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "commands.md"

INTRO = """\
# Commands

`cfm-fem COMMAND --help` prints the options of a command; this page holds the same text for
every command (generated from the parser by `python scripts/make_commands_doc.py`), with an
example above each list. `python -m cfm_fem` is the same program as `cfm-fem`.

Every command: exit code 0 on success, 2 on bad input (one message naming the file, line and
column and what was expected; nothing written), 1 when interrupted (Ctrl-C). A command that
writes into `--out DIR` holds a lock on `DIR/.cfm_fem.lock` while it runs; a second run into the
same folder stops at once with exit code 2, naming the run that holds it. Long work shows a
progress bar on a terminal and a plain progress line every few seconds when the output goes to
a file. Numeric options take finite numbers only (`nan`, `inf` stop at the option), and a run
whose trials or rows would not fit in the memory available stops before any work, saying how
many fit. What each command writes is described in [outputs.md](outputs.md); the input files in
[formats.md](formats.md).
"""

#: (command, example, summary, what it is for); the parser decides which commands are listed
#: and in which order (`commands`).
EXAMPLES = [
    (
        "sweep",
        "cfm-fem sweep meshes/quadrupole.vtu --up 0:50:10 --out results/",
        "U_f maps of a field map for a sweep of U_p",
        "Per-node U_f maps of a field map for a sweep of positioning uncertainties U_p "
        "(Monte Carlo, GUM Supplement 1). `--mode htm` draws the probe error from the bench "
        "model instead of N(0, U_p). `--pieces`, `--slabs`/`--max-memory`, `--workers`/"
        "`--scheduler` and `--resume` change how the work is split, never the numbers. The "
        "U_f percentiles weigh each node by the volume it stands for; `--region` takes them over "
        "a box or a cylinder (the good-field region); `--table csv` adds a per-node table.",
    ),
    (
        "design",
        "cfm-fem design meshes/quadrupole.vtu --uf-max 40 --region cylinder:7,-30:30 --out design/",
        "largest U_p that keeps U_f <= X units",
        "The paper's design question: the largest U_p that keeps U_f at or below a target over "
        "a share of the nodes (default 95 %) of the map or of a `--region`, with its Monte Carlo "
        "uncertainty. Writes the sweep's outputs, `design.json` and a report with the answer on "
        "top. With `--quantity Q --max X --r-ref MM`: the largest U_p that keeps U95 of a "
        "field-quality figure of `cfm-fem quality` (b_n, a_n, centre, roll, length) within X, "
        "by bisection with the quality Monte Carlo in mode gauss; writes `design.json`.",
    ),
    (
        "kinematics",
        "cfm-fem kinematics --trials 100000 --out kin/",
        "positioning error of the bench (Table IV)",
        "The probe positioning error of the bench at the 936 points of the scan grid: the 21 "
        "geometric errors, vibration and reading delay through the exact HTM chain (paper "
        "Table IV), with the uncertainty budget per error and axis.",
    ),
    (
        "tolerance",
        "cfm-fem tolerance --target 15 --out tol/",
        "tolerances for a target U_p",
        "Design in reverse: how far each of the 21 tolerances may be loosened, or must be "
        "tightened, to meet a target U_p per axis.",
    ),
    (
        "coupled",
        "cfm-fem coupled --out coupled/",
        "field error of positioning and probe together (Table V)",
        "Field error from positioning and Hall probe together on a multipole or a field map "
        "(paper eq. 12-14, pooled as Table V), with an HTML report.",
    ),
    (
        "quality",
        "cfm-fem quality meshes/quadrupole.vtu --r-ref 10 --mode htm --out quality/",
        "field quality of a map and how well the bench determines it",
        "Integrated harmonics b_n, a_n at R_ref, magnetic centre, roll and magnetic length of a "
        "field map, with the U95 of each from the bench (Monte Carlo of the scan, adaptive) "
        "and the budget by error group; a particle's deflection with `--rigidity`. Method and "
        "outputs: [quality.md](quality.md).",
    ),
    (
        "fig4",
        "cfm-fem fig4 meshes/quadrupole.vtu --out fig4/",
        "U_f against U_p (Fig. 4)",
        "U_f against U_p on a field map as a table and plots (paper Fig. 4).",
    ),
    (
        "synth",
        "cfm-fem synth tracker --out rec/tracker.csv",
        "a synthetic recording of a simulated bench",
        "A synthetic laser-tracker recording or Hall map of one simulated bench (one draw of its "
        "errors; the same seed gives the same file), in the recording contract: input for "
        "`compare` and `diagnose`, and a way to try them without a bench.",
    ),
    (
        "compare",
        "cfm-fem compare --tracker rec/tracker.csv --out cmp/",
        "recordings against the simulation",
        "Recordings (laser tracker or Hall-probe map) against the simulation: experimental "
        "Table IV / V, standardised residuals per point, interval views (paper Fig. 12, 13), "
        "ISO 230-2 of single-axis bidirectional runs.",
    ),
    (
        "diagnose",
        "cfm-fem diagnose --tracker rec/tracker.csv --out diag/",
        "why simulation and recording disagree",
        "Where simulation and recording disagree, and why: calibrates the bench, locates "
        "significant residuals, attributes them to a catalogue of physical effects, refits "
        "and advises. Method and validation: [diagnosis.md](diagnosis.md).",
    ),
]


def _subcommands() -> dict:
    """The parser's subcommands, name -> subparser, in the order ``cfm-fem --help`` lists them."""
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal width: fixed for the page
    from cfm_fem.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def commands() -> list[tuple[str, str, str, str]]:
    """(command, example, summary, what it is for) of every subcommand of the parser.

    Raises
    ------
    SystemExit
        A subcommand without an entry in `EXAMPLES`, or an entry for no subcommand.
    """
    names = list(_subcommands())
    known = {row[0]: row for row in EXAMPLES}
    missing = [n for n in names if n not in known]
    extra = [n for n in known if n not in names]
    if missing or extra:
        raise SystemExit(
            f"{Path(__file__).name}: "
            + (f"add an EXAMPLES entry for {', '.join(missing)}" if missing else "")
            + ("; " if missing and extra else "")
            + (f"no such command: {', '.join(extra)}" if extra else "")
        )
    return [known[n] for n in names]


def help_text(name: str) -> str:
    """``cfm-fem NAME --help`` at 100 columns."""
    return _subcommands()[name].format_help().rstrip() + "\n"


def page() -> str:
    rows = commands()
    parts = [INTRO]
    parts.append("| command | what for |\n|---|---|\n")
    parts.append("".join(f"| [`{name}`](#{name}) | {short} |\n" for name, _, short, _ in rows))
    for name, example, _, what in rows:
        parts.append(f"\n## {name}\n\n{what}\n\n    {example}\n\n```text\n{help_text(name)}```\n")
    return "\n".join(parts[:1]) + "\n" + "".join(parts[1:])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 if the page is out of date")
    args = p.parse_args(argv)
    text = page()
    if args.check:
        if PAGE.read_text(encoding="utf-8") != text:
            print(f"{PAGE} is out of date: run python scripts/make_commands_doc.py")
            return 1
        return 0
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
