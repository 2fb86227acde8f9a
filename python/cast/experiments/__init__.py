"""``cast sweep``: a design comparison run as many ``cast run`` processes, with its report and plots.

docs/experiments.md.
"""
