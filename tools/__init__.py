"""Developer tools kept out of the installed packages (run from a checkout)."""
