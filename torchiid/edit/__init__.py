"""Editing with a decomposition: the paper's applications and a few more.

Every function works on batches of **linear** RGB tensors: images and reflectances
``(B, 3, H, W)``, shadings ``(B, 1, H, W)`` (gray, as :func:`torchiid.decompose` returns them)
or ``(B, 3, H, W)`` (coloured, as :func:`merge` returns them), masks ``(B, 1, H, W)`` bool
(``True`` = inside). Nothing is clipped except where a docstring says so; clip to ``[0, 1]``
(or let :func:`torchiid.save_image` do it) to display a result.

One module per operation:

* :mod:`~torchiid.edit.merging` — :func:`merge`, the merged components of the two stages (the
  step the paper's applications start from): merged shading and reflectance and the
  illumination colour approximation ``C``.
* :mod:`~torchiid.edit.tint` — :func:`illumination_colour`, tint the light near the brightest
  (directly lit) regions.
* :mod:`~torchiid.edit.intensity` — :func:`illumination_intensity`, raise indirectly lit
  regions, keep directly lit ones.
* :mod:`~torchiid.edit.flatten` — :func:`remove_texture`, and :mod:`~torchiid.edit.retexture`
  — :func:`replace_albedo`: retexturing inside a mask.
* :mod:`~torchiid.edit.recolouring` — :func:`recolour`, change hue/chroma of an object's
  reflectance inside a mask.
* :mod:`~torchiid.edit.shadows` — :func:`soften_shadows`, compress (or expand) the
  log-shading's range.

:mod:`~torchiid.edit.colour` holds the named tints, colour parsing and CIELab,
:mod:`~torchiid.edit.common` the Gaussian filter and the shape checks.
:class:`Merge`, :class:`IlluminationColour`, :class:`IlluminationIntensity`, :class:`Recolour`
and :class:`SoftenShadows` are ``nn.Module`` twins holding the options.
"""

from torchiid.edit.colour import COLOURS, lab_to_linear, linear_to_lab, parse_colour
from torchiid.edit.common import default_blur, gaussian
from torchiid.edit.common import white_level as _white  # noqa: F401 - the CLI's shading view
from torchiid.edit.flatten import remove_texture
from torchiid.edit.intensity import COMBINE as COMBINE
from torchiid.edit.intensity import IlluminationIntensity, illumination_intensity
from torchiid.edit.merging import Merge, Merged, merge
from torchiid.edit.recolouring import Recolour, recolour
from torchiid.edit.retexture import replace_albedo
from torchiid.edit.shadows import SoftenShadows, soften_shadows
from torchiid.edit.tint import IlluminationColour, illumination_colour, light_weights

__all__ = [
    "COLOURS",
    "IlluminationColour",
    "IlluminationIntensity",
    "Merge",
    "Merged",
    "Recolour",
    "SoftenShadows",
    "default_blur",
    "gaussian",
    "illumination_colour",
    "illumination_intensity",
    "linear_to_lab",
    "lab_to_linear",
    "light_weights",
    "merge",
    "parse_colour",
    "recolour",
    "remove_texture",
    "replace_albedo",
    "soften_shadows",
]
