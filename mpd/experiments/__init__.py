"""Declarative experiment specs, the runner (local and Ray), data-versioned results and run tracking."""
