"""`make demo`: the simulated controller, a sample job, a live progress display."""
