"""The chaos soak (``python -m bench.chaos``): promises checked from outside under a seeded schedule.

``schedule`` draws the steps from the seed (pure); ``wire`` is the plain Zenoh client of the
wire contract; ``run`` is the shell (the twin's processes, the lanes, the final disable);
``trace`` holds what was seen; ``monitors`` and ``limits`` judge it (pure); ``selftest`` shows
each monitor able to fail. docs/benchmarks.md, "Chaos soak".
"""
