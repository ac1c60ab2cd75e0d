"""Recording (MCAP, raw) and replay (paced, through the live pipeline)."""
