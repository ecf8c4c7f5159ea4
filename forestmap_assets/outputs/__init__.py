"""What forestmap shows and writes: the exports of a run, ``report.html``, the 2-D figures of
every stage, the 3-D render of the map, ``forestmap solve``'s tables, and terminal progress.

May import: ``core``, ``io``, ``sim`` (truth for the report), ``access``, ``params``, ``outputs``;
never ``assets`` or ``orchestration``.
"""
