"""Single-frame encoders (registry filled in once all modules exist)."""
