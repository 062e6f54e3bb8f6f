"""Pure analysis of flight data shared by the companion, the demo report and the CLI (no I/O)."""
