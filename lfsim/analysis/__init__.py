"""Analysis and plots: layouts, spot diagrams, reports."""
