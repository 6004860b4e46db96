"""Leaf types and services every layer shares: poses and angle wrapping, records, errors, timing,
progress, and the one JIT warm-up."""
