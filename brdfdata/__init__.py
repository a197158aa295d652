"""What a BRDF measurement is as data, shared by every layer above it (docs/design.md §2–§4).

=================  ============================================================================
module             what it holds
=================  ============================================================================
``directions``     the angle conventions: spherical ↔ vector in the sample frame, reflection,
                   uniform hemisphere directions
``rusinkiewicz``   half/difference angles (θ_h, θ_d, φ_d) for isotropic materials
``samples``        the samples table, its contract (the guards) and its Parquet files
``formats``        the formats other instruments write: RGL, MERL, delimited text
``sniff``          which of those a file is, by its first bytes
``coverage``       which regions of the hemisphere a set of direction pairs reaches
``data_paths``     where the real data files are found ($GONIO_DATA, data/, the wheel, a cache)
=================  ============================================================================

Acquisition, calibration and fitting all speak this vocabulary; it imports only
:mod:`plumbing` (import-linter contract), so none of them reaches another through it.
"""
