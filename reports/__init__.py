"""Self-contained HTML reports (plotly), built from the results store only."""
