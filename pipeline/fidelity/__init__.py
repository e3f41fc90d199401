"""Fidelity of the spring network: an independent continuum (finite-element) reference.

See docs/design/validation.md.
"""
