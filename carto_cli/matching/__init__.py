"""Scan matchers: real-time correlative, least squares, branch and bound."""
