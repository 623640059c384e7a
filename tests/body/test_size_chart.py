"""Tests of the built-in size chart."""

from __future__ import annotations

import pytest

from torchgarment.body.size_chart import INCH, SIZES, UNDERBUST_RATIO, chart_row, list_sizes
from torchgarment.errors import InputError


def test_sizes_smallest_first_and_monotonic():
    assert list_sizes() == list(SIZES) == ["6", "8", "10", "12", "14", "16", "18", "20"]
    rows = [chart_row(s) for s in SIZES]
    for key in ("bust", "underbust", "waist", "hips"):
        values = [r[key] for r in rows]
        assert all(b > a for a, b in zip(values, values[1:])), key


def test_row_values_in_metres_from_source():
    row = chart_row("12")
    assert set(row) == {"height", "bust", "underbust", "waist", "hips"}
    assert row["bust"] == pytest.approx(34.0 * INCH)
    assert row["waist"] == pytest.approx(26.5 * INCH)
    assert row["hips"] == pytest.approx(36.0 * INCH)
    assert row["height"] == pytest.approx(1.6637, abs=1e-4)
    assert row["underbust"] == pytest.approx(row["bust"] * UNDERBUST_RATIO)
    assert 0.8 < UNDERBUST_RATIO < 0.85
    assert chart_row(12) == row


def test_unknown_size_lists_valid_sizes():
    with pytest.raises(InputError, match="valid sizes: 6, 8, 10"):
        chart_row("XL")
