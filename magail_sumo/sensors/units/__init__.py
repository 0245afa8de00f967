"""The built-in sensor units, one module each; importing the package imports every module in
it, which registers its sensors (:func:`magail_sumo.sensors.base.register`): a new sensor is one
new module here."""

import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")
