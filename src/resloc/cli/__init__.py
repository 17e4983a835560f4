"""Command-line interface (thin: parse, call an importable ``run_*`` function, save)."""
