"""`hilbo review`: plots, a report and CSV tables of a session from its MCAP log(s)."""
