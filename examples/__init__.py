"""Example task factories for `task: package.module:factory` (docs/tasks.md)."""
