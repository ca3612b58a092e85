"""The particle tasks and custom PettingZoo tasks behind one TaskEnv, and
their vectorized worlds. Imports shared.core and the environment libraries."""
