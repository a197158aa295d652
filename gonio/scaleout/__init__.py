"""Fits spread over a Dask cluster (issue 20): per texel (`gonio fit-texels`) and per table of a
material library (`gonio fit-batch`). The science is in fitting.texels and fitting.fit; these
modules only distribute it and keep its results crash-safe.

===========  ================================================================================
module       what it holds
===========  ================================================================================
``cluster``  the Dask client, crash-safe result files, the output folder's job claim
``texels``   per-texel jobs: chunks of texels as tasks, written as they complete
``batch``    per-table jobs over a folder or glob of samples tables
``maps``     parameter maps of a per-texel fit: PNG previews, EXR textures, a Mitsuba scene
===========  ================================================================================
"""
