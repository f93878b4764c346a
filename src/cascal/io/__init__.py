"""File input and output: CSV data, model files, atomic writes. The numerical core never imports this."""
