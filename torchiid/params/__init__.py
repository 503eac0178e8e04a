"""Parameters of the method: :class:`Parameters`, its groups, presets and ablation variants.

:class:`Parameters` is made of the groups the stages take (:class:`FeatureParameters`,
:class:`ShadingParameters`, :class:`ReflectanceParameters`, :class:`OutputParameters`) and the
schedule of the alternations; every leaf field documents itself (:mod:`torchiid.params.fields`).
:data:`PRESETS` and :data:`VARIANTS` are in the flat form of a parameter file, and
:data:`ADDED_SINCE` records, by version, the parameters added since the parameter set took its
present shape (:mod:`torchiid.params.files`).
"""

from torchiid.params.files import ADDED_SINCE
from torchiid.params.groups import FeatureParameters, OutputParameters
from torchiid.params.parameters import Parameters
from torchiid.params.presets import PRESETS, VARIANTS
from torchiid.params.reflectance import ReflectanceParameters
from torchiid.params.shading import ShadingParameters

__all__ = [
    "Parameters",
    "FeatureParameters",
    "ShadingParameters",
    "ReflectanceParameters",
    "OutputParameters",
    "PRESETS",
    "VARIANTS",
    "ADDED_SINCE",
]
