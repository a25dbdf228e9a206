"""The ipt profile's pairs: the compiled CIEDE2000, the clip allowance (least CIEDE2000, within its budget),
the frame kernel against the pairs, the complete table and its cache file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from test_invisibility import SHARMA_PAIRS

from ipt.invisibility import ciede2000
from ipt.sender import framekernel, pairs
from ipt.sender.colour import L8_PER_LSTAR, LUMINANCE_WEIGHTS, code_to_lab, code_to_linear, linear_to_lab, lstar
from ipt.sender.modulator import IptModulator, PaperModulator
from ipt.sender.pairs import COLOURS, allowance_budget_de00
from ipt.sender.pairtable import PairTable, cache_path, read_cache, write_cache

U8 = npt.NDArray[np.uint8]
DELTA_L = 4.0
CORNERS = np.array(
    [(255, 255, 255), (255, 255, 0), (0, 255, 255), (0, 255, 0), (255, 0, 255), (255, 0, 0), (0, 0, 255), (0, 0, 0)],
    np.uint8,
)


def _step_l8(up: U8, down: U8) -> npt.NDArray[np.float64]:
    y_up, y_down = code_to_linear(up) @ LUMINANCE_WEIGHTS, code_to_linear(down) @ LUMINANCE_WEIGHTS
    out: npt.NDArray[np.float64] = (lstar(y_up) - lstar(y_down)) * L8_PER_LSTAR
    return out


def _fused_de(codes: U8, up: U8, down: U8) -> npt.NDArray[np.float64]:
    fused = (code_to_linear(up) + code_to_linear(down)) / 2
    return ciede2000(code_to_lab(codes), linear_to_lab(fused))


def _near_the_gamut(n: int, seed: int) -> U8:
    """Colours where the allowance works: channels at or next to 0 and 255, mixed with random ones."""
    rng = np.random.default_rng(seed)
    ends = rng.choice(np.array([0, 1, 2, 3, 5, 250, 252, 253, 254, 255], np.uint8), (n, 3))
    mixed = ends.copy()
    mixed[: n // 2, rng.integers(0, 3)] = rng.integers(0, 256, n // 2)
    return np.concatenate([CORNERS, ends, mixed])


def test_compiled_ciede2000_matches_the_published_test_data_and_the_numpy_one() -> None:
    for lab1, lab2, expected in SHARMA_PAIRS:
        assert pairs._de00_c(*lab1, *lab2) == pytest.approx(expected, abs=5e-5)
        assert pairs._de00_c(*lab2, *lab1) == pytest.approx(expected, abs=5e-5)
    rng = np.random.default_rng(0)
    lin = rng.uniform(0, 1, (500, 2, 3))
    lab = linear_to_lab(lin)
    want = ciede2000(lab[:, 0], lab[:, 1])
    got = [pairs._de00_c(*lab[k, 0], *lab[k, 1]) for k in range(len(lab))]
    assert np.allclose(got, want, atol=1e-9)
    assert all(np.allclose(pairs._lab_c(*lin[k, 0]), lab[k, 0], atol=1e-9) for k in range(len(lab)))


def test_the_budget_is_what_the_allowance_costs_at_white() -> None:
    assert allowance_budget_de00(0.0) == 0.0
    assert allowance_budget_de00(2.0) == pytest.approx(0.4505, abs=1e-4)
    white, grey = np.array([100.0, 0, 0]), np.array([100.0 - 2.2 / L8_PER_LSTAR, 0, 0])
    assert allowance_budget_de00(2.2) == pytest.approx(float(ciede2000(white, grey)), abs=1e-12)
    with pytest.raises(pairs.PairsError, match="clip allowance"):
        allowance_budget_de00(float("nan"))


@pytest.mark.parametrize("allowance", [1.0, 2.0, 2.2, 4.0])
def test_no_fused_colour_misses_the_input_by_more_than_the_budget(allowance: float) -> None:
    table = PairTable(DELTA_L, allowance)
    exact = PairTable(DELTA_L, 0.0)
    codes = _near_the_gamut(3000, seed=int(allowance * 10))
    up, down = table.pairs(codes)
    de = _fused_de(codes, up, down)
    # The exact pair's own 8-bit error is the floor (below the budget except for tiny allowances).
    e_up, e_down = exact.pairs(codes)
    floor = _fused_de(codes, e_up, e_down)
    assert np.all(de <= np.maximum(table.budget_de00, floor) + 1e-9)
    # ... and the allowance is spent: the step grows wherever the exact pair fell short.
    short = _step_l8(e_up, e_down) < 2 * DELTA_L - 1.0
    assert np.mean(_step_l8(up, down)[short] > _step_l8(e_up, e_down)[short] + 0.5) > 0.9


def test_the_allowance_costs_least_on_saturated_colours() -> None:
    # The same budget buys more step on pure primaries than moving their lightness would (the old way,
    # and the paper's clipping): about the paper's signal everywhere, more on red, blue and magenta.
    table = PairTable(DELTA_L, 2.0)
    up, down = table.pairs(CORNERS)
    step, de = _step_l8(up, down), _fused_de(CORNERS, up, down)
    assert np.all(de <= table.budget_de00 + 1e-9)
    assert np.all(step > 3.3), step
    paper = PaperModulator(np.ones((1, len(CORNERS)), np.int8), DELTA_L)
    p_up, p_down = (f[0] for f in paper.phases(CORNERS[None]))
    paper_step = _step_l8(p_up, p_down)
    for k in (4, 5, 6):  # magenta, red, blue
        assert step[k] > paper_step[k] + 0.8, (CORNERS[k], step[k], paper_step[k])
    assert step.sum() > paper_step.sum()


def test_colours_with_room_are_not_touched_by_the_allowance() -> None:
    rng = np.random.default_rng(6)
    middle = rng.integers(30, 226, (5000, 3), dtype=np.uint8)
    for a, b in zip(PairTable(DELTA_L, 0.0).pairs(middle), PairTable(DELTA_L, 2.0).pairs(middle), strict=True):
        assert np.array_equal(a, b)


def _reference_frames(table: PairTable, rgb: U8, mask: npt.NDArray[np.int8]) -> tuple[U8, U8]:
    up, down = table.pairs(rgb.reshape(-1, 3))
    up, down = up.reshape(rgb.shape), down.reshape(rgb.shape)
    plus, minus = rgb.copy(), rgb.copy()
    white, black = mask > 0, mask < 0
    plus[white], minus[white] = up[white], down[white]
    plus[black], minus[black] = down[black], up[black]
    return plus, minus


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 3), (37, 61)])
def test_the_kernel_writes_what_the_pairs_say_to_the_last_byte(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    mask = rng.integers(-1, 2, shape).astype(np.int8)
    mask.flat[-1] = 1  # the last pixel (written byte by byte) a tag pixel
    mod = IptModulator(mask, DELTA_L, clip_allowance_l8=2.0)
    want = _reference_frames(mod._pairs, rgb, mask)
    # Outputs that hold other bytes already, and a guard byte past each: nothing outside is written.
    for fill in (0, 255):
        plus = np.full(rgb.size + 1, fill, np.uint8)
        minus = np.full(rgb.size + 1, fill, np.uint8)
        out = (plus[:-1].reshape(rgb.shape), minus[:-1].reshape(rgb.shape))
        got = mod.phases(rgb, out)
        assert np.array_equal(got[0], want[0])
        assert np.array_equal(got[1], want[1])
        assert plus[-1] == fill
        assert minus[-1] == fill
        for sign, frame in ((1, want[0]), (-1, want[1])):
            assert np.array_equal(mod.phase_frame(rgb, sign), frame)


def test_rows_in_parts_and_threads_give_the_same_frames() -> None:
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (97, 53, 3), dtype=np.uint8)
    mask = rng.integers(-1, 2, rgb.shape[:2]).astype(np.int8)
    one = IptModulator(mask, DELTA_L, clip_allowance_l8=2.0)
    three = IptModulator(mask, DELTA_L, threads=3, clip_allowance_l8=2.0)
    try:
        want = one.phases(rgb)
        big = np.ascontiguousarray(np.tile(rgb, (2, 2, 1)))  # 194 rows: split over the threads
        big_mask = np.tile(mask, (2, 2))
        got = IptModulator(big_mask, DELTA_L, threads=3, clip_allowance_l8=2.0).phases(big)
        assert np.array_equal(got[0][:97, :53], want[0])
        assert np.array_equal(got[1][97:, 53:], want[1])
        parts = (np.zeros_like(rgb), np.zeros_like(rgb))
        for r0, r1 in ((0, 1), (1, 40), (40, 40), (40, 97)):
            three.phases_rows(rgb, parts, r0, r1)
        assert np.array_equal(parts[0], want[0])
        assert np.array_equal(parts[1], want[1])
    finally:
        three.close()


# --- the complete table and its cache ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def complete(tmp_path_factory: pytest.TempPathFactory) -> tuple[PairTable, Path]:
    """A complete table for ΔL 4 and allowance 2 (computed once; a quarter of a minute on 2 cores), cached."""
    folder = tmp_path_factory.mktemp("pair-cache")
    table = PairTable(DELTA_L, 2.0)
    lines: list[str] = []
    said = table.complete_with_cache(folder, lines.append)
    assert table.complete
    assert said.startswith("colour table: computed in")
    assert str(folder) in said
    assert any("100%" in line for line in lines)  # progress was reported
    return table, cache_path(folder, DELTA_L, 2.0)


def test_the_complete_table_holds_what_each_colour_computes(complete: tuple[PairTable, Path]) -> None:
    table, _ = complete
    assert np.all(table.table & pairs._VALID)
    assert table.spot_check(table.table, count=20_000, seed=3) == 0
    lazy = PairTable(DELTA_L, 2.0)
    codes = _near_the_gamut(2000, seed=4)
    for a, b in zip(lazy.pairs(codes), table.pairs(codes), strict=True):
        assert np.array_equal(a, b)


def test_the_cache_is_read_back_and_checked(complete: tuple[PairTable, Path], tmp_path: Path) -> None:
    table, path = complete
    header = json.loads(path.read_bytes()[8:4096].decode())
    assert header["version"] == pairs.ALGORITHM_VERSION
    assert header["entries"] == COLOURS
    again = PairTable(DELTA_L, 2.0)
    said = again.complete_with_cache(path.parent, lambda _: None)
    assert said.startswith(f"colour table: read {path}")
    assert again.complete
    assert np.array_equal(again.table, table.table)
    # Another table's file is not taken for this one.
    other = PairTable(DELTA_L, 3.0)
    assert read_cache(path, other) == "made for another table (clip_allowance_l8)"
    assert not other.complete
    # Damaged, truncated, not a table at all: refused, the table left as it was.
    data = bytearray(path.read_bytes())
    for name, content, problem in (
        ("flipped", data[:5000] + bytes([data[5000] ^ 1]) + data[5001:], "checksum mismatch (damaged)"),
        ("short", data[:-8], "truncated or too long"),
        ("junk", b"hello" * 1000, "not a pair table"),
    ):
        bad = tmp_path / name
        bad.write_bytes(bytes(content))
        fresh = PairTable(DELTA_L, 2.0)
        assert read_cache(bad, fresh) == problem
        assert not fresh.complete
    # A file whose checksum is right but whose entries another version of the maths made (the version
    # number not bumped): the sample recomputed on loading catches it.
    forged = PairTable(DELTA_L, 2.0)
    forged.table = table.table ^ np.uint64(1)
    forged.complete = True
    write_cache(tmp_path / "forged", forged)
    problem = read_cache(tmp_path / "forged", PairTable(DELTA_L, 2.0))
    assert problem == "its entries differ from what this version computes"


def test_a_damaged_cache_is_computed_again_and_replaced(complete: tuple[PairTable, Path], tmp_path: Path) -> None:
    table, path = complete
    target = cache_path(tmp_path, DELTA_L, 2.0)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    target.write_bytes(bytes(data))
    stale = tmp_path / "pairs-v1-dl4-a2.bin"
    stale.write_bytes(b"old")
    lines: list[str] = []
    again = PairTable(DELTA_L, 2.0)
    said = again.complete_with_cache(tmp_path, lines.append)
    assert lines[0] == f"colour table: {target}: checksum mismatch (damaged); computing it again"
    assert said.startswith("colour table: computed in")
    assert np.array_equal(again.table, table.table)
    assert target.read_bytes() == path.read_bytes()  # replaced by a good one
    assert not stale.exists()  # a file of an older version can never be read again: removed
    assert [p.name for p in tmp_path.iterdir() if "partial" in p.name] == []


def test_a_cache_that_cannot_be_written_is_said_and_the_table_still_completes(
    complete: tuple[PairTable, Path], tmp_path: Path
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    again = PairTable(DELTA_L, 2.0)
    again.table = complete[0].table.copy()  # every entry there already: filling finds nothing left to do
    said = again.complete_with_cache(blocker / "sub", lambda _: None)
    assert again.complete
    assert said.startswith("colour table: computed in")
    assert f"cannot keep it in {cache_path(blocker / 'sub', DELTA_L, 2.0)}" in said
    assert said.endswith("computed at every start")
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


@pytest.mark.parametrize("threads", [1, 3])
def test_a_complete_table_takes_the_kernel_without_colour_maths_and_gives_the_same_frames(
    complete: tuple[PairTable, Path], threads: int
) -> None:
    rng = np.random.default_rng(8)
    rgb = rng.integers(0, 256, (131, 67, 3), dtype=np.uint8)  # 131 rows: split over 3 threads
    rgb[:5] = CORNERS[rng.integers(0, len(CORNERS), (5, 67))]  # pure colours, where the allowance moves pairs
    mask = rng.integers(-1, 2, rgb.shape[:2]).astype(np.int8)
    mask.flat[-1] = -1  # the last pixel (written byte by byte) a black tag pixel
    lazy = IptModulator(mask, DELTA_L, clip_allowance_l8=2.0)
    filled = IptModulator(mask, DELTA_L, threads=threads, clip_allowance_l8=2.0)
    filled._pairs = complete[0]
    try:
        assert filled._kernel() is framekernel._modulate_rows_filled_c
        want = _reference_frames(complete[0], rgb, mask)
        for fill in (0, 255):
            plus = np.full(rgb.size + 1, fill, np.uint8)
            minus = np.full(rgb.size + 1, fill, np.uint8)
            got = filled.phases(rgb, (plus[:-1].reshape(rgb.shape), minus[:-1].reshape(rgb.shape)))
            assert np.array_equal(got[0], want[0])
            assert np.array_equal(got[1], want[1])
            assert (plus[-1], minus[-1]) == (fill, fill)  # nothing written past the frame
        for sign, frame in ((1, want[0]), (-1, want[1])):
            assert np.array_equal(filled.phase_frame(rgb, sign), frame)
            assert np.array_equal(lazy.phase_frame(rgb, sign), frame)
        parts = (np.zeros_like(rgb), np.zeros_like(rgb))
        for r0, r1 in ((0, 1), (1, 70), (70, 70), (70, 131)):
            filled.phases_rows(rgb, parts, r0, r1)
        assert np.array_equal(parts[0], want[0])
        assert np.array_equal(parts[1], want[1])
        region = (3, 7, 40, 90)
        crop = np.ascontiguousarray(rgb[7:90, 3:40])
        assert np.array_equal(filled.phase_region(crop, 1, region), want[0][7:90, 3:40])
    finally:
        filled.close()
