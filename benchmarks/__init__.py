"""Speed and accuracy benchmarks of flyvpr; never imported by the package itself.

``from benchmarks.accuracy_report import render_markdown`` turns the JSON written by
``python benchmarks/accuracy.py --json FILE`` into Markdown tables.
"""
