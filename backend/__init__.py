"""kgs_backend: the FastAPI service behind `kgs-app serve` (imports kgs_core only)."""
