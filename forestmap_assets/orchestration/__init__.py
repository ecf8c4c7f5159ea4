"""Running the pipeline through Dagster: the workspace's definitions, the runner behind
``forestmap run`` and ``status``, executors, automation (sensor, schedule), UI and notebooks.

May import everything below it: ``assets``, ``outputs``, ``io``, ``core``, ``params``.
"""
