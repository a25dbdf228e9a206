"""Arena config and camera_info loading: the shipped values, strictness, and one clear error per bad file."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

import ipt.config.base as base_module
import ipt.config.models as models_module
import ipt.config.pipeline as pipeline_module
from ipt.config import (
    ArenaConfig,
    CameraInfo,
    CameraInfoError,
    ConfigError,
    PipelineConfig,
    TagMapConfig,
    load_arena_config,
    load_camera_info,
    load_yaml_model,
    save_camera_info,
    shipped_config_path,
)
from ipt.errors import IptError


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def _dump(tmp_path: Path, name: str, data: Any) -> Path:
    return _write(tmp_path, name, yaml.safe_dump(data, sort_keys=False))


# --- the shipped arena ---------------------------------------------------------------------------------


def test_shipped_arena_has_the_papers_values() -> None:
    path = shipped_config_path("arena.yaml")
    assert path.is_file()
    arena = load_arena_config(path)
    assert (arena.projector.width_px, arena.projector.height_px) == (1920, 2160)
    assert arena.projector.rate_hz == pytest.approx(60.0)
    assert (arena.screen.width_m, arena.screen.height_m) == (pytest.approx(2.17), pytest.approx(2.47))
    assert (arena.tag_map.rows, arena.tag_map.cols) == (9, 9)
    assert arena.tag_map.family == "tag36h11"
    assert arena.tag_map.first_id == 0
    assert arena.modulation.profile == "ipt"  # the colour-exact profile; "paper" stays available
    assert arena.modulation.delta_l == pytest.approx(4.0)
    assert arena.modulation.input_rate_hz == pytest.approx(30.0)


def test_shipped_arena_equals_the_model_defaults_but_for_its_landing_pad() -> None:
    # The defaults and the shipped file describe the same (paper) arena, the shipped one with a landing pad
    # of small tags (issue 15); any other drift between them is a bug.
    shipped = load_arena_config(shipped_config_path("arena.yaml"))
    assert [p.name for p in shipped.tag_map.pads] == ["pad-a"]
    no_pads = shipped.model_copy(update={"tag_map": shipped.tag_map.model_copy(update={"pads": ()})})
    assert no_pads == ArenaConfig()


def test_partial_file_keeps_defaults_for_the_rest(tmp_path: Path) -> None:
    arena = load_arena_config(_dump(tmp_path, "a.yaml", {"modulation": {"delta_l": 6}}))
    assert arena.modulation.delta_l == pytest.approx(6.0)
    assert arena.projector == ArenaConfig().projector
    assert arena.tag_map == ArenaConfig().tag_map


def test_models_are_frozen() -> None:
    arena = ArenaConfig()
    with pytest.raises(ValidationError, match="frozen"):
        arena.projector.width_px = 10  # type: ignore[misc]


# --- arena errors ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "dotted"),
    [
        ({"projector": {"widht_px": 1920}}, "projector.widht_px"),
        ({"tag_map": {"rows": 9, "colums": 9}}, "tag_map.colums"),
        ({"modulaton": {"delta_l": 4}}, "modulaton"),
    ],
)
def test_unknown_key_names_file_and_dotted_path(tmp_path: Path, data: dict[str, Any], dotted: str) -> None:
    path = _dump(tmp_path, "typo-arena.yaml", data)
    with pytest.raises(ConfigError) as info:
        load_arena_config(path)
    msg = str(info.value)
    assert str(path) in msg
    assert f"{dotted}: unknown key" in msg
    assert "\n" not in msg


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=r"nope\.yaml") as info:
        load_arena_config(path)
    assert "no such file" in str(info.value)


def test_directory_instead_of_file(tmp_path: Path) -> None:
    d = tmp_path / "somedir.yaml"
    d.mkdir()
    with pytest.raises(ConfigError, match=r"somedir\.yaml"):
        load_arena_config(d)


@pytest.mark.parametrize(
    ("name", "text", "fragment"),
    [
        ("empty.yaml", "", "empty"),
        ("comments-only.yaml", "# nothing here\n", "empty"),
        ("syntax.yaml", "projector:\n  width_px: [1920\n", "not valid YAML"),
        ("tabs.yaml", "projector:\n\twidth_px: 1920\n", "not valid YAML"),
        ("list.yaml", "- projector\n- screen\n", "mapping"),
        ("scalar.yaml", "42\n", "mapping"),
        ("wrongtype.yaml", "projector:\n  width_px: wide\n", "projector.width_px"),
        ("section-not-mapping.yaml", "projector: 1920\n", "projector"),
        ("fraction.yaml", "tag_map:\n  rows: 2.5\n", "tag_map.rows"),
        ("range.yaml", "screen:\n  width_m: -1\n", "screen.width_m"),
        ("family.yaml", "tag_map:\n  family: tag16h5\n", "tag_map.family"),
        ("not8.yaml", "tag_map:\n  tag_size_px: 100\n", "multiple of 8"),
        ("ids.yaml", "tag_map:\n  first_id: 550\n", "587"),
        ("nofit-cols.yaml", "tag_map:\n  cols: 12\n", "12 columns"),
        ("nofit-rows.yaml", "projector:\n  height_px: 1000\n", "9 rows"),
    ],
)
def test_bad_arena_files_raise_config_error_naming_the_file(
    tmp_path: Path, name: str, text: str, fragment: str
) -> None:
    path = _write(tmp_path, name, text)
    with pytest.raises(ConfigError) as info:
        load_arena_config(path)
    msg = str(info.value)
    assert msg.startswith(str(path) + ":"), msg
    assert fragment in msg
    assert "\n" not in msg


def test_syntax_error_reports_the_line(tmp_path: Path) -> None:
    path = _write(tmp_path, "bad.yaml", "projector:\n  width_px: 1920\n  height_px: [2160\nscreen: {}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML at line \d+"):
        load_arena_config(path)


def test_config_errors_are_ipt_errors() -> None:
    assert issubclass(ConfigError, IptError)
    assert issubclass(CameraInfoError, IptError)


def test_tag_fit_boundary() -> None:
    # 9 columns of 160 px tags with 20 px quiet zones need 9 * 200 = 1800 px: 1800 fits, 1799 does not.
    ArenaConfig.model_validate({"projector": {"width_px": 1800}})
    with pytest.raises(ValueError, match="do not fit"):
        ArenaConfig.model_validate({"projector": {"width_px": 1799}})


def test_tag_size_multiple_of_8_accepted_and_rejected() -> None:
    assert TagMapConfig(tag_size_px=168).tag_size_px == 168
    with pytest.raises(ValueError, match="multiple of 8"):
        TagMapConfig(tag_size_px=164)


def test_load_yaml_model_other_models(tmp_path: Path) -> None:
    cfg = load_yaml_model(_dump(tmp_path, "p.yaml", {"detector": {"quad_decimate": 2.0}}), PipelineConfig)
    assert cfg.detector.quad_decimate == pytest.approx(2.0)
    assert cfg.demodulation == PipelineConfig().demodulation
    path = _dump(tmp_path, "q.yaml", {"pose": {"min_tagz": 2}})
    with pytest.raises(ConfigError, match=r"pose\.min_tagz: unknown key"):
        load_yaml_model(path, PipelineConfig)


@pytest.mark.parametrize("decimate", [1.0, 1.5, 2.0, 3.0, 8.0])
def test_quad_decimate_apriltag_carries_out_is_taken(decimate: float) -> None:
    assert PipelineConfig.model_validate({"detector": {"quad_decimate": decimate}}).detector.quad_decimate == decimate


@pytest.mark.parametrize("decimate", [1.25, 1.75, 2.5])
def test_quad_decimate_apriltag_would_misplace_is_refused(tmp_path: Path, decimate: float) -> None:
    path = _dump(tmp_path, "p.yaml", {"detector": {"quad_decimate": decimate}})
    with pytest.raises(ConfigError, match=r"detector\.quad_decimate: .*not a factor AprilTag carries out") as err:
        load_yaml_model(path, PipelineConfig)
    assert "\n" not in str(err.value)


# --- every field described -------------------------------------------------------------------------------


def _all_models() -> list[type[BaseModel]]:
    """Every model defined in the settings modules that ``ipt.config.models`` gathers."""
    found = [
        obj
        for module in (base_module, models_module, pipeline_module)
        for obj in vars(module).values()
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == module.__name__
    ]
    return sorted(found, key=lambda m: m.__name__)


def _walk_fields(model: type[BaseModel], prefix: str, seen: set[type[BaseModel]]) -> list[tuple[str, str | None]]:
    if model in seen:
        return []
    seen.add(model)
    out: list[tuple[str, str | None]] = []
    for name, field in model.model_fields.items():
        out.append((f"{prefix}{name}", field.description))
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out.extend(_walk_fields(ann, f"{prefix}{name}.", seen))
    return out


def test_every_field_of_every_model_is_described() -> None:
    models = _all_models()
    names = {m.__name__ for m in models}
    assert {"ArenaConfig", "PipelineConfig", "DetectorConfig", "DemodulationConfig", "PoseConfig"} <= names
    walked = 0
    for model in models:
        for dotted, desc in _walk_fields(model, f"{model.__name__}.", set()):
            walked += 1
            assert desc is not None, f"{dotted} has no description"
            assert desc.strip(), f"{dotted} has an empty description"
    # ArenaConfig alone has 4 sections with 3+2+5+3 fields.
    assert walked >= 4 + 13


def test_every_model_forbids_unknown_keys() -> None:
    for model in _all_models():
        if model.__name__ == "StrictModel":
            continue
        assert model.model_config.get("extra") == "forbid", model.__name__


# --- camera_info -----------------------------------------------------------------------------------------

_ROS_CAMERA: dict[str, Any] = {
    "image_width": 640,
    "image_height": 360,
    "camera_name": "down_cam",
    "camera_matrix": {"rows": 3, "cols": 3, "data": [452.5, 0.0, 320.25, 0.0, 451.0, 179.75, 0.0, 0.0, 1.0]},
    "distortion_model": "plumb_bob",
    "distortion_coefficients": {"rows": 1, "cols": 5, "data": [-0.12, 0.034, 0.001, -0.002, 0.0005]},
    "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
    "projection_matrix": {
        "rows": 3,
        "cols": 4,
        "data": [452.5, 0.0, 320.25, 0.0, 0.0, 451.0, 179.75, 0.0, 0.0, 0.0, 1.0, 0.0],
    },
}

# The way camera_calibration writes it (flow style matrices, block style top level).
_ROS_CAMERA_TEXT = """\
image_width: 640
image_height: 360
camera_name: down_cam
camera_matrix:
  rows: 3
  cols: 3
  data: [452.5, 0, 320.25, 0, 451, 179.75, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.12, 0.034, 0.001, -0.002, 0.0005]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [452.5, 0, 320.25, 0, 0, 451, 179.75, 0, 0, 0, 1, 0]
"""


def _camera_variant(**changes: Any) -> dict[str, Any]:
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in _ROS_CAMERA.items()}
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        else:
            data[key] = value
    return data


def test_ros_camera_info_loads(tmp_path: Path) -> None:
    info = load_camera_info(_write(tmp_path, "camera.yaml", _ROS_CAMERA_TEXT))
    assert (info.width_px, info.height_px) == (640, 360)
    assert info.fx_px == pytest.approx(452.5)
    assert info.fy_px == pytest.approx(451.0)
    assert info.cx_px == pytest.approx(320.25)
    assert info.cy_px == pytest.approx(179.75)
    assert info.distortion == pytest.approx((-0.12, 0.034, 0.001, -0.002, 0.0005))
    assert info.name == "down_cam"
    k = info.camera_matrix
    assert k.shape == (3, 3)
    assert k[0, 0] == pytest.approx(452.5)
    assert k[1, 1] == pytest.approx(451.0)
    assert k[0, 2] == pytest.approx(320.25)
    assert k[1, 2] == pytest.approx(179.75)
    assert k[2, 2] == 1.0
    assert k[0, 1] == 0.0
    assert info.dist_coeffs.shape == (5,)


def test_camera_info_without_distortion_defaults_to_zero(tmp_path: Path) -> None:
    info = load_camera_info(_dump(tmp_path, "c.yaml", _camera_variant(distortion_coefficients=None)))
    assert info.distortion == (0.0, 0.0, 0.0, 0.0, 0.0)


def test_camera_info_column_distortion_vector(tmp_path: Path) -> None:
    dist = {"rows": 5, "cols": 1, "data": [0.1, 0.2, 0.3, 0.4, 0.5]}
    info = load_camera_info(_dump(tmp_path, "c.yaml", _camera_variant(distortion_coefficients=dist)))
    assert info.distortion == pytest.approx((0.1, 0.2, 0.3, 0.4, 0.5))


def test_camera_info_round_trip(tmp_path: Path) -> None:
    info = CameraInfo(
        width_px=1280,
        height_px=720,
        fx_px=901.125,
        fy_px=899.5,
        cx_px=639.3,
        cy_px=361.7,
        distortion=(0.01, -0.02, 0.0003, 0.0004, -0.005),
        name="rig_cam",
    )
    path = tmp_path / "saved.yaml"
    save_camera_info(info, path)
    assert load_camera_info(path) == info
    # A ROS tool would read what we wrote: check the raw mapping too.
    raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    assert raw["distortion_model"] == "plumb_bob"
    assert raw["camera_matrix"]["data"][0] == pytest.approx(901.125)
    assert raw["projection_matrix"]["rows"] == 3
    assert raw["projection_matrix"]["cols"] == 4
    assert not list(tmp_path.glob("*.partial*")), "no temporary file left behind"


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"camera_matrix": None}, "camera_matrix"),
        ({"camera_matrix": {"rows": 2, "cols": 3, "data": [1, 0, 1, 0, 1, 1]}}, "unexpected shape 2x3"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 1, 0, 1, 1, 0, 0]}}, "needs 9 values"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [500, 0, 320, 0, "f", 180, 0, 0, 1]}}, "finite number"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [500, 0, 320, 0, True, 180, 0, 0, 1]}}, "finite number"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [-500, 0, 320, 0, 500, 180, 0, 0, 1]}}, "focal"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [500, 0, 320, 0, 500, 180, 0, 0, 2]}}, "camera_matrix"),
        ({"camera_matrix": [500, 0, 320, 0, 500, 180, 0, 0, 1]}, "camera_matrix"),
        ({"distortion_coefficients": {"rows": 1, "cols": 3, "data": [0, 0, 0]}}, "distortion_coefficients"),
        ({"distortion_model": "equidistant"}, "equidistant"),
        ({"image_width": None}, "image_width"),
        ({"image_width": 0}, "image_width"),
        ({"image_height": "tall"}, "image_height"),
        ({"image_height": True}, "image_height"),
        ({"frame_id": "cam"}, "frame_id"),
    ],
)
def test_bad_camera_info_raises_naming_the_file(tmp_path: Path, changes: dict[str, Any], fragment: str) -> None:
    path = _dump(tmp_path, "bad-camera.yaml", _camera_variant(**changes))
    with pytest.raises(CameraInfoError) as info:
        load_camera_info(path)
    msg = str(info.value)
    assert msg.startswith(str(path) + ":"), msg
    assert fragment in msg
    assert "\n" not in msg


def test_camera_info_non_finite_value(tmp_path: Path) -> None:
    text = _ROS_CAMERA_TEXT.replace("data: [452.5, 0, 320.25", "data: [.inf, 0, 320.25")
    path = _write(tmp_path, "inf.yaml", text)
    with pytest.raises(CameraInfoError, match=r"inf\.yaml: camera_matrix"):
        load_camera_info(path)


@pytest.mark.parametrize(
    ("name", "text"),
    [("missing.yaml", None), ("empty.yaml", ""), ("syntax.yaml", "a: [1\n"), ("list.yaml", "- 1\n")],
)
def test_camera_info_unreadable_files(tmp_path: Path, name: str, text: str | None) -> None:
    path = tmp_path / name if text is None else _write(tmp_path, name, text)
    with pytest.raises(CameraInfoError, match=name.replace(".", r"\.")):
        load_camera_info(path)


def test_arena_yaml_is_not_a_camera_info(tmp_path: Path) -> None:
    with pytest.raises(CameraInfoError, match="unknown key"):
        load_camera_info(shipped_config_path("arena.yaml"))


def test_camera_info_mixed_type_unknown_keys(tmp_path: Path) -> None:
    path = _write(tmp_path, "mixed.yaml", "1: a\nb: c\n")
    with pytest.raises(CameraInfoError, match=r"mixed\.yaml"):
        load_camera_info(path)


def test_camera_info_huge_integer(tmp_path: Path) -> None:
    path = _dump(tmp_path, "huge.yaml", _camera_variant(camera_matrix={"rows": 3, "cols": 3, "data": [10**400] * 9}))
    with pytest.raises(CameraInfoError, match=r"huge\.yaml"):
        load_camera_info(path)


@pytest.mark.parametrize("loader", [load_arena_config, load_camera_info])
def test_error_for_key_with_newline_is_one_line(tmp_path: Path, loader: Any) -> None:
    path = _write(tmp_path, "nl.yaml", '"bad\\nkey": 1\n')
    with pytest.raises((ConfigError, CameraInfoError)) as info:
        loader(path)
    assert "\n" not in str(info.value)


# --- property: arbitrary YAML data never escapes as anything but the module's own error ----------------

_KEYS = st.one_of(
    st.sampled_from(
        [
            "projector",
            "screen",
            "tag_map",
            "modulation",
            "width_px",
            "height_px",
            "rate_hz",
            "width_m",
            "height_m",
            "rows",
            "cols",
            "tag_size_px",
            "first_id",
            "delta_l",
            "image_width",
            "image_height",
            "camera_name",
            "camera_matrix",
            "distortion_model",
            "distortion_coefficients",
            "data",
        ]
    ),
    st.text(max_size=8),
)
_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
_YAML_DATA = st.recursive(
    _SCALARS,
    lambda children: st.one_of(
        st.lists(children, max_size=10),
        st.dictionaries(_KEYS, children, max_size=6),
    ),
    max_leaves=30,
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=_YAML_DATA)
def test_arbitrary_yaml_raises_only_config_errors(tmp_path: Path, data: Any) -> None:
    path = _write(tmp_path, "any.yaml", yaml.safe_dump(data))
    messages = []
    for model in (ArenaConfig, PipelineConfig):
        try:
            load_yaml_model(path, model)
        except ConfigError as exc:
            messages.append(str(exc))
    try:
        load_camera_info(path)
    except CameraInfoError as exc:
        messages.append(str(exc))
    # Anything else propagates and fails the test; every error starts with the file name.
    for msg in messages:
        assert msg.startswith(f"{path}: ")


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    fx=st.floats(allow_nan=True, allow_infinity=True),
    cy=st.one_of(st.floats(allow_nan=True), st.text(max_size=4), st.none()),
    ncoef=st.integers(0, 9),
)
def test_camera_matrix_values_raise_only_camera_info_errors(tmp_path: Path, fx: float, cy: Any, ncoef: int) -> None:
    data = _camera_variant(
        camera_matrix={"rows": 3, "cols": 3, "data": [fx, 0.0, 320.0, 0.0, 450.0, cy, 0.0, 0.0, 1.0]},
        distortion_coefficients={"rows": 1, "cols": ncoef, "data": [0.0] * ncoef},
    )
    path = _dump(tmp_path, "cam.yaml", data)
    ok = math.isfinite(fx) and fx > 0 and isinstance(cy, float) and math.isfinite(cy) and ncoef in (4, 5, 8)
    ok = ok and 0.05 * 640 <= fx <= 20 * 640 and -0.5 <= cy <= 359.5  # a real camera's intrinsics (issue 33)
    if ok:
        info = load_camera_info(path)
        assert info.fx_px == fx
        assert info.cy_px == cy
        assert len(info.distortion) == ncoef
    else:
        with pytest.raises(CameraInfoError, match=r"cam\.yaml"):
            load_camera_info(path)
