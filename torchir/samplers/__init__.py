"""Stateful samplers (adaptive pixel sampling, ReSTIR reservoirs). Filled by their issues."""
