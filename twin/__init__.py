"""drives-twin: a simulated twin of a fleet file (router + one bus agent per host), with fault
injection and link cuts, for users' networked integration tests; ``twin.pytest_plugin`` offers
it as pytest fixtures."""

from .plan import PlanError
from .twin import Twin, TwinError

__all__ = ["PlanError", "Twin", "TwinError"]
