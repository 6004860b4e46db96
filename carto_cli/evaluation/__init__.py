"""Measuring what a run produced: trajectory metrics, CI gates, timing reports, relocalization evaluation."""
