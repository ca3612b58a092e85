"""Math and learners: counting, SimHash, bonuses, networks, replay and the
MADDPG learners. Imports numpy and torch only (and nothing above it in shared/)."""
