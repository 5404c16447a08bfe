"""Metrics, the accuracy-versus-time benchmark and the HTML report."""
