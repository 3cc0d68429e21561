"""Pure study code: the Kim et al. 2019 test functions and protocol, the tutoring model (Antonova 2016)."""
