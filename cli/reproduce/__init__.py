"""`macb reproduce`: the thesis's figures run, analysed and published, laid out by what
each part does:

- defs.py, figures.py: what a figure is, and the thesis's figures as data;
- claims.py: the checks that measure each claim;
- experiments.py: a figure's arms as configs, as an experiment, and their controls;
- analysis.py: the curves smoothed, their spread over seeds, the claims' verdicts;
- controls.py: each counting arm against its control, and why (count-1, bonus paid);
- render.py, plot.py: the page (FIGURE.md, .csv.gz, -claims.json) and FIGURE.png;
- status.py: how far a `--local` campaign got, read from its runs' folders;
- page.py: a `--local` campaign's page from its runs' folders;
- slurm.py: `--local --launcher slurm`, the run groups as the tasks of a Slurm array job;
- command.py, session.py: the command, in this process or through the API.
"""

from cli.reproduce.command import add_reproduce_parser, cmd_reproduce

__all__ = ["add_reproduce_parser", "cmd_reproduce"]
