"""Run groups' names for their callers: the one trainer (cli/trainer.py) trains R >= 1
runs, a run alone being a group of one."""

from cli.trainer import GroupRun, Member, train_group

__all__ = ["GroupRun", "Member", "train_group"]
