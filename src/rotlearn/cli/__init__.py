"""Floor 4: command-line entry points (Hydra mains)."""
