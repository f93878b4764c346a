"""File input and output: CSV data, model files, atomic writes (never used by the core)."""
