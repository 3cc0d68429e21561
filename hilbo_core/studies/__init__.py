"""Pure study code: the seed-000 test functions and protocol, the tutoring model (seed 003)."""
