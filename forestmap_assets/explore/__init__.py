"""``forestmap explore``: a virtual survey that scans where the planner says, registers each new
scan and stops when the plot is covered, against survey-grid and random baselines (men_spec 7).

May import: ``core``, ``sim``, ``io``, ``outputs``, ``access``, ``assets``, ``orchestration``.
"""
