"""Reports: the self-contained report.html, its figures, summaries and formatting."""
