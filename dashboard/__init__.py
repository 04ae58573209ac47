"""``drives-dashboard``: the fleet as a live web page and Prometheus metrics, a thin view over
``supervisor.Fleet`` (view.py: state; metrics.py: Prometheus; app.py: ASGI; cli.py: the program)."""
