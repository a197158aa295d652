"""Values, not only types, in a samples table (issue 22, item 3): flags that a cast would turn
into 0 (= good) — 2³², NaN, null, fractions, negatives — and rows with no channel name are
refused in one line naming the column and the row; a valid table still loads."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from brdfdata.samples import SamplesError, SampleTable, read_samples, write_samples


def _valid(path) -> pa.Table:
    n = 4
    table = SampleTable(
        theta_i=np.full(n, 0.3),
        phi_i=np.zeros(n),
        theta_o=np.linspace(0.1, 0.9, n),
        phi_o=np.full(n, np.pi),
        channel=np.array(["G"] * n),
        f=np.full(n, 0.2),
        sigma=np.full(n, 0.01),
        flags=np.zeros(n, np.int32),
    )
    write_samples(path, table)
    return pq.read_table(path)


def _with(arrow: pa.Table, name: str, values: pa.Array, path) -> None:
    i = arrow.schema.get_field_index(name)
    pq.write_table(arrow.set_column(i, name, values), path)


@pytest.mark.parametrize(
    ("values", "words"),
    [
        (pa.array([0, 0, 2**32, 0], pa.int64()), "row 2 holds 4.29497e+09"),
        (pa.array([0.0, np.nan, 0.0, 0.0], pa.float64()), "row 1 holds nan"),
        (pa.array([0, None, 0, 0], pa.int64()), "row 1 is null"),
        (pa.array([0.0, 0.0, 0.5, 0.0], pa.float64()), "row 2 holds 0.5"),
        (pa.array([0, 0, 0, -1], pa.int64()), "row 3 holds -1"),
    ],
)
def test_flags_a_cast_would_hide_are_refused(tmp_path, values, words) -> None:
    path = tmp_path / "s.parquet"
    arrow = _valid(path)
    _with(arrow, "flags", values, tmp_path / "bad.parquet")
    with pytest.raises(SamplesError, match=words.replace("+", r"\+")):
        read_samples(tmp_path / "bad.parquet")


def test_a_row_without_a_channel_is_refused(tmp_path) -> None:
    arrow = _valid(tmp_path / "s.parquet")
    _with(arrow, "channel", pa.array(["G", None, "G", "G"]), tmp_path / "bad.parquet")
    with pytest.raises(SamplesError, match="row 1 has no channel name"):
        read_samples(tmp_path / "bad.parquet")


def test_valid_flags_still_load(tmp_path) -> None:
    arrow = _valid(tmp_path / "s.parquet")
    _with(arrow, "flags", pa.array([0, 8, 2**31 - 1, 0], pa.int64()), tmp_path / "ok.parquet")
    t = read_samples(tmp_path / "ok.parquet")
    assert t.flags.tolist() == [0, 8, 2**31 - 1, 0]


def test_dictionary_encoded_channels_still_load(tmp_path) -> None:
    # Other tools write string columns dictionary-encoded; that is still text.
    arrow = _valid(tmp_path / "s.parquet")
    _with(arrow, "channel", pa.array(["G"] * 4).dictionary_encode(), tmp_path / "d.parquet")
    assert read_samples(tmp_path / "d.parquet").channel.tolist() == ["G"] * 4


@pytest.mark.parametrize("bad", [np.nan, -0.5])
def test_a_bend_level_the_fit_cannot_use_is_refused_in_one_line(tmp_path, bad) -> None:
    """The fit multiplies each row's model by 1 + b · bend_level (fitting.nuisance): a NaN in a
    row the fit uses would turn every likelihood into NaN, a failed fit with no word of why:
    measured rows and rows whose flag keeps or censors them alike. An excluded row may hold
    anything."""
    arrow = _valid(tmp_path / "s.parquet")
    level = pa.array([0.2, bad, 0.4, 0.5], pa.float32())
    pq.write_table(arrow.append_column("bend_level", level), tmp_path / "bad.parquet")
    with pytest.raises(SamplesError, match="column 'bend_level' holds .* in row 1"):
        read_samples(tmp_path / "bad.parquet")
    flagged = arrow.set_column(
        arrow.schema.get_field_index("flags"), "flags", pa.array([0, 8, 0, 0], pa.int32())
    )
    pq.write_table(flagged.append_column("bend_level", level), tmp_path / "ok.parquet")
    assert read_samples(tmp_path / "ok.parquet").extra["bend_level"][2] == pytest.approx(0.4)
    for kept_or_censored in (16, 1):  # negative (kept as measured), saturated (censored)
        marked = arrow.set_column(
            arrow.schema.get_field_index("flags"),
            "flags",
            pa.array([0, kept_or_censored, 0, 0], pa.int32()),
        )
        pq.write_table(marked.append_column("bend_level", level), tmp_path / "marked.parquet")
        with pytest.raises(SamplesError, match="column 'bend_level' holds .* in row 1"):
            read_samples(tmp_path / "marked.parquet")


def test_the_hash_is_of_the_bytes_read_and_a_file_changed_meanwhile_is_refused(
    tmp_path, monkeypatch
) -> None:
    """Issue 47: the table's SHA-256 (which a fit records and a report compares) was taken by a
    second read after the first, so a file rewritten in between passed with the new file's hash
    on the old file's values. Now the hash is of the bytes parsed, and a file whose bytes differ
    once the read is over is refused in one line. The other writer is a stand-in (its timing
    cannot be made deterministic): it rewrites the file right after gonio's read returns."""
    import brdfdata.samples.files as files
    from plumbing.hashing import sha256_file

    path = tmp_path / "s.parquet"
    pq.write_table(_valid(tmp_path / "x.parquet"), path)
    assert read_samples(path).source_sha256 == sha256_file(path)
    changed = _valid(tmp_path / "y.parquet")
    changed = changed.set_column(
        changed.column_names.index("f"), "f", pa.array(np.asarray(changed["f"]) * 1.5)
    )
    real_read = files.read_input_bytes

    def read_then_rewritten(*args, **kwargs):
        data = real_read(*args, **kwargs)
        pq.write_table(changed, path)  # the other program's write lands now
        return data

    monkeypatch.setattr(files, "read_input_bytes", read_then_rewritten)
    with pytest.raises(SamplesError, match="changed while gonio read it") as e:
        read_samples(path)
    assert "\n" not in str(e.value) and "s.parquet" in str(e.value)
