"""The steps of :func:`~torchiid.model.decompose`, each in the module that owns it.

:mod:`~torchiid.pipeline.inputs` (the inputs at the working resolution),
:mod:`~torchiid.pipeline.alternation` (the shading and reflectance steps and their reports),
:mod:`~torchiid.pipeline.layers` (the layers at the input's resolution),
:mod:`~torchiid.pipeline.results` (what a decomposition returns) and
:mod:`~torchiid.pipeline.memory` (the memory estimate checked before any work). The public
names are importable from :mod:`torchiid.model`.
"""
