"""Temporal filters (registry filled in once all modules exist)."""
