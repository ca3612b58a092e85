"""The fields of a metric row, in one place: the trainer's CSV, the services' rows and
the API's store and CSV all use these names, in this order. (No numpy or torch here:
the API imports it.)"""

TRAIN_FIELDS = (
    "episode",
    "env_steps",
    "success_rate",
    "eval_return",
    "collisions_cum",
    "count1_pct",
    "table_size",
    "counted_transitions",
    "bonus_mean",
    "bonus_std",
    "sampled_count1_pct",
    "steps_per_sec",
    "train_steps_per_sec",
    "updates",
    "wall_s",
)
# What a distributed run adds to each row.
SERVICE_FIELDS = ("replay_ratio", "policy_lag", "policy_version")
ALL_FIELDS = TRAIN_FIELDS + SERVICE_FIELDS
