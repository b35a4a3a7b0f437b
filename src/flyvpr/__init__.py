"""flyvpr: visual place recognition with FlyNet+CANN (package init under construction)."""

__version__ = "0.1.0"
