"""Solution methods for joints, limits and contacts, one module each: ``spring`` (penalty forces and velocity
impulses, in the spirit of Brax v1) and ``xpbd`` (position-based projection, after Mueller et al. 2020, "Detailed
Rigid Body Simulation with Extended Position Based Dynamics").

Each module ends with its :class:`Method` record (``torchsim.methods._method``); ``METHODS`` collects every
module's record by name, so adding a method is adding a module.
"""

import importlib
import pkgutil

from torchsim.methods._method import Method

METHODS: dict[str, Method] = {}
for _module in pkgutil.iter_modules(__path__):
    if _module.name.startswith("_"):
        continue
    _method = importlib.import_module(f"{__name__}.{_module.name}").METHOD
    METHODS[_method.name] = _method
