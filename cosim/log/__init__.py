"""The log of a run: MCAP writing and reading (`mcap`), and figures made from it (`plot`)."""
