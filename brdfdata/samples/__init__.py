"""The BRDF samples table (docs/design.md §4): the contract between calibration and fitting.

=============  ==========================================================================
module         what it holds
=============  ==========================================================================
``table``      the table in memory: columns, flags and what each does, schema version,
               ``SamplesError``
``guards``     the unit and range checks every source of samples passes (the contract's
               rules: degrees, below-horizon rows, σ ≤ 0, negative f, duplicates)
``files``      ``samples.parquet`` on disk: atomic whole and streamed writes, the checked read
=============  ==========================================================================

Import from here: ``from brdfdata.samples import SampleTable, read_samples``.
"""

from __future__ import annotations

from brdfdata.samples.files import (
    SampleStream,
    check_columns,
    open_samples_file,
    read_samples,
    table_from_arrow,
    write_samples,
    write_samples_streamed,
)
from brdfdata.samples.guards import GuardError, check_samples, merge_duplicates
from brdfdata.samples.table import (
    CHANNELS,
    DARK_SNR,
    FLAG_ROLES,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    SCHEMA_VERSION,
    Flags,
    RowKinds,
    SamplesError,
    SampleTable,
    dark_snr_of,
    row_kinds,
)

__all__ = [
    "SCHEMA_VERSION",
    "REQUIRED_COLUMNS",
    "OPTIONAL_COLUMNS",
    "CHANNELS",
    "Flags",
    "FLAG_ROLES",
    "RowKinds",
    "row_kinds",
    "DARK_SNR",
    "dark_snr_of",
    "SampleTable",
    "SamplesError",
    "GuardError",
    "check_samples",
    "merge_duplicates",
    "read_samples",
    "write_samples",
    "write_samples_streamed",
    "SampleStream",
    "open_samples_file",
    "check_columns",
    "table_from_arrow",
]
