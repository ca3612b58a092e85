"""A run's parts built from its config: the learner and exploration
(factories) and collection and evaluation (rollout)."""
