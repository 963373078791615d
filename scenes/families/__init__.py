"""Scene families: one module each, with ``generate(seed) -> GeneratedScene``."""
