"""The options of each job, declared once: `kgs-app synth`, `ingest`, `export` and `train` build
their command lines from these models (`kgs_app.cli_args.add_options`) and the server takes them
as request bodies, so a bound, a default or a choice cannot disagree between the two, and a bad
value is refused with the same words by both. Training's settings are `train.config.TrainConfig`:
`TrainOptions` offers the ones in `train.settings.NAMED` as typed fields, and any other as a
checked `KEY=VALUE`.

What is not an option of the job stays outside: the files it reads and writes (paths on the
command line; uploads and workspace folders on the server) and whether to replace them.
"""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, create_model, field_validator, model_validator

from .data.synth.scenes import SCENES

# The choices of the options below, for the modules that act on them.
BLURS = ("none", "mild", "severe")  # a synthetic scene's exposure: 0, 0.5 or 1 frame interval
MAPPERS = ("auto", "keyframes", "global", "incremental")
LENSES = ("opencv", "simple")
FORMATS = ("ply-seq", "splat", "splatv", "mp4", "glb")

SceneName = Literal[tuple(sorted(SCENES))]  # type: ignore[valid-type]


class JobOptions(BaseModel):
    """Unknown fields and non-finite numbers are refused, naming the field."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# Synthetic scenes: each bound alone allows 1024² x 2000 x 64 rendered pixels (days of CPU) or
# 1024² x 2000 stored (tens of GB), so their products are bounded too.
MAX_SYNTH_PIXELS = 1 << 31  # rendered: e.g. 512² x 512 x 16; the demo's 128² x 60 x 16 = 2^24
MAX_SYNTH_FRAME_PIXELS = 1 << 27  # stored (about 16 bytes a pixel on disk): 1024² x 128, 512² x 512


class SynthOptions(JobOptions):
    """A built-in synthetic scene (`kgs_core.data.synth.generate.synthesize`). Bounds: size² x
    frames at most 2^27 pixels stored (about 2 GB on disk), size² x frames x max(subframes,
    pixel_grid²) at most 2^31 rendered."""

    name: SceneName = Field("sheet", description="the built-in scene")  # type: ignore[valid-type]
    blur: Literal[BLURS] = Field("mild", description="exposure 0, 0.5 or 1 frame interval")  # type: ignore[valid-type]
    seed: int = Field(0, ge=0, le=2**31 - 1, description="the scene's textures and motion")
    size: int = Field(128, ge=16, le=1024, description="image width and height, in pixels")
    frames: int = Field(60, ge=2, le=2000, description="frames in the clip")
    subframes: int = Field(16, ge=1, le=64, description="sharp renders averaged per blurry frame")
    pixel_grid: int = Field(3, ge=1, le=7, description="rays per pixel side of a sharp frame (odd; 1: one ray, aliased)")

    @model_validator(mode="after")
    def bounded_work(self) -> "SynthOptions":
        if self.pixel_grid % 2 == 0:
            raise ValueError(f"pixel_grid must be odd (its centre ray gives the masks), got {self.pixel_grid}")
        stored = self.size * self.size * self.frames
        if stored > MAX_SYNTH_FRAME_PIXELS:
            raise ValueError(f"size² x frames is {stored:,}, above {MAX_SYNTH_FRAME_PIXELS:,} (lower one of them)")
        renders = stored * max(self.subframes, self.pixel_grid**2)
        if renders > MAX_SYNTH_PIXELS:
            raise ValueError(f"size² x frames x max(subframes, pixel_grid²) is {renders:,}, above {MAX_SYNTH_PIXELS:,} (lower one of them)")
        return self


# The long side frames are kept at by default: BARD-GS's full size, so that every training budget
# can use the detail; a training's time budget picks what it affords.
DEFAULT_MAX_SIZE = 960


class IngestOptions(JobOptions):
    """How a video becomes a scene (`kgs_core.data.ingest.ingest`)."""

    max_size: int = Field(DEFAULT_MAX_SIZE, ge=64, le=4096, description="long side of the frames, in pixels")
    every: int | None = Field(None, ge=1, le=1000, description="keep every k-th frame (default: all, or about 300 of a longer video)")
    max_frames: int | None = Field(None, ge=2, le=100_000, description="keep at most this many frames from the start")
    mapper: Literal[MAPPERS] = Field(  # type: ignore[valid-type]
        "auto",
        description="SfM mapper: keyframes (fast), global (GLOMAP), incremental (slowest, most robust); auto "
        "reuses the poses of an earlier ingest of the same frames at any max_size, else tries keyframes, then "
        "incremental; a named mapper always maps anew",
    )
    lens: Literal[LENSES] = Field(  # type: ignore[valid-type]
        "opencv",
        description="lens model: opencv refits each camera after mapping with two focal lengths, two radial "
        "and two tangential terms, kept where it lowers the reprojection error; simple keeps SfM's one focal length "
        "and one radial term (docs/data.md)",
    )
    holdout_every: int | None = Field(
        None, ge=0, le=1000, description="with one video, every n-th frame is a test view (0: none; default 8)"
    )
    fixed_camera: bool = Field(False, description="the camera does not move (a tripod): skip SfM, one pose for every frame")
    keep_distortion: bool = Field(
        False,
        description="keep the SfM camera's lens distortion instead of undistorting "
        "frames to pinhole (the rasteriser is pinhole: only for export to other tools)",
    )
    exposure: float = Field(0.5, ge=0, le=1, description="the training video's exposure, a fraction of the frame interval")

    @field_validator("holdout_every")
    @classmethod
    def holdout_not_one(cls, value: int | None) -> int | None:
        if value == 1:
            raise ValueError("must be 0 (none) or at least 2")
        return value

    def ingest_arguments(self) -> dict:
        """The keyword arguments of `kgs_core.data.ingest.ingest` these options are."""
        kw = self.model_dump(exclude={"keep_distortion"})
        return {**kw, "undistort": not self.keep_distortion}


class ViewCamera(JobOptions):
    """One camera for a video from a fixed view (the viewer's current one)."""

    viewmat: list[list[float]] = Field(description="4x4 world-to-camera (OpenCV axes), row-major")
    fov_deg: float = Field(ge=1, lt=179, description="horizontal field of view")
    width: int = Field(ge=16, le=4096)
    height: int = Field(ge=16, le=4096)

    @model_validator(mode="after")
    def a_rotation(self) -> "ViewCamera":
        from .export.camera_path import view_path

        view_path(self.model_dump(), [0.0])  # a matrix that is not 4x4, or whose rotation is not one
        return self


class ExportOptions(JobOptions):
    """A run as files (`kgs_core.export.export_run`)."""

    format: Literal[FORMATS] = Field(description="what to write (docs/exports.md)")  # type: ignore[valid-type]
    times: str | None = Field(
        None, max_length=10000, description="T, T1,T2,... or START:STOP:COUNT in [0, 1] (default: the training frames' times)"
    )
    camera_path: Literal["training", "orbit", "view"] = Field(
        "training", description="mp4: along the training cameras, once round the scene, or held at `view`"
    )
    view: ViewCamera | None = Field(None, description="the camera of camera_path view")
    exposure: float = Field(0.0, ge=0, le=1, description="shutter fraction to bake in (0: sharp)")
    lod: int | None = Field(None, ge=1, description="LoD level (default: the finest)")
    side_by_side: bool = Field(False, description="mp4 on the training cameras: the input frame beside each render")
    size: int | None = Field(None, ge=16, le=4096, description="mp4: the video's long side in pixels (default: the cameras' own)")
    fps: float = Field(24.0, gt=0, le=240, description="mp4: frames a second")
    web_frame: bool | None = Field(
        None,
        description="write .ply, .splat or .splatv so that antimatter15/splat or "
        "splaTV opens on the first training camera's view (default: on for splat and "
        "splatv; the transform is in export.json)",
    )

    def export_arguments(self) -> dict:
        """The keyword arguments of `kgs_core.export.export_run` these options are."""
        return {
            "fmt": self.format,
            **self.model_dump(exclude={"format", "view"}),
            "view": None if self.view is None else self.view.model_dump(),
        }

    @field_validator("times")
    @classmethod
    def times_parse(cls, value: str | None) -> str | None:
        from .export.bake import parse_times

        parse_times(value, [])
        return value

    @model_validator(mode="after")
    def options_fit_the_format(self) -> "ExportOptions":
        from .export.bake import parse_times

        if (self.camera_path == "view") != (self.view is not None):
            raise ValueError("camera_path view and a view go together")
        if self.side_by_side and self.camera_path != "training":
            raise ValueError("side_by_side needs camera_path training")
        if self.size is not None and self.format != "mp4":
            raise ValueError("size sets a video's resolution: only with format mp4")
        if self.web_frame and self.format not in ("ply-seq", "splat", "splatv"):
            raise ValueError(f"web_frame is for ply-seq, splat and splatv, not {self.format}")
        if self.format == "glb" and len(parse_times(self.times, [0.5])) != 1:
            raise ValueError("glb exports one time: give one time")
        return self


class TrainOptionsBase(JobOptions):
    """How to train (`kgs_core.train.config.make_config`): a preset, ablations, and settings."""

    preset: str = Field(
        "fast",
        description="fast: minutes on two cores, fitted to the scene; paper: the paper's 30k-iteration schedule with five LoD levels",
    )
    ablate: list[str] = Field([], max_length=16, description="parts of the method to leave out (or comma-separated)")
    settings: list[str] = Field(
        [],
        max_length=64,
        description="KEY=VALUE of any training setting (a TrainConfig "
        "field, model.FIELD or densify.FIELD), checked against the schema and applied last",
    )
    config: Any = Field(
        None,
        description="any training setting, typed: {FIELD: VALUE, model: {FIELD: VALUE}, "
        "densify: {FIELD: VALUE}}, applied after the named ones and before `settings`",
    )

    @field_validator("preset")
    @classmethod
    def known_preset(cls, value: str) -> str:
        from .train.config import PRESETS

        if value not in PRESETS:
            raise ValueError(f"unknown preset {value!r}; one of {', '.join(sorted(PRESETS))}")
        return value

    @field_validator("ablate", mode="before")
    @classmethod
    def known_ablations(cls, value: Any) -> Any:
        from .train.config import check_ablations

        if isinstance(value, str):
            value = [value]
        if isinstance(value, list):  # "kr,cf" on the command line
            value = [a for v in value for a in (v.split(",") if isinstance(v, str) else [v]) if a != ""]
            check_ablations(value)
        return value

    @field_validator("settings")
    @classmethod
    def settings_in_schema(cls, value: list[str]) -> list[str]:
        from .train.settings import parse_setting

        for text in value:
            parse_setting(text)  # a ValueError naming the key
        return value

    @model_validator(mode="after")
    def device_here(self) -> "TrainOptionsBase":
        """A device this machine lacks is refused with the options, before a scene is read or
        a job queued."""
        from .device import resolve_device

        device = self.overrides().get("device")
        if device is not None:
            resolve_device(device, "device")
        return self

    def overrides(self) -> dict:
        """`make_config` overrides: the named settings given, then `settings` over them."""
        from .train.settings import NAMED, named_overrides, parse_setting

        out = named_overrides({name: getattr(self, name, None) for name in NAMED})
        if self.config is not None:
            given = self.config.model_dump(exclude_none=True)
            for part in ("model", "densify"):
                out.update({f"{part}.{k}": v for k, v in (given.pop(part, None) or {}).items()})
            out.update(given)
        out.update(parse_setting(text) for text in self.settings)
        return out


def _named_field(name: str) -> tuple[object, object]:
    """A field for a setting offered by name: the schema's type (optional: None is the preset's
    value), its bounds (`settings.bound`) and its help; read from a string as the setting's own
    parser reads it (a duration: `10m`)."""
    from .train.settings import NAMED, bound, setting_type

    named = NAMED[name]
    kind: Any = setting_type(named.key)
    if named.parse is not None:
        parse = named.parse
        kind = Annotated[kind, BeforeValidator(lambda v: parse(v) if isinstance(v, str) else v)]
    limits = bound(named.key)
    if limits is None:
        return kind | None, Field(None, description=named.help)
    return (
        kind | None,
        Field(
            None, gt=limits.low if limits.above else None, ge=None if limits.above else limits.low, le=limits.high, description=named.help
        ),
    )


def _checked(key: str, value):
    from .train.settings import check_setting

    return check_setting(key, value)


def _training_settings() -> type[BaseModel]:
    """Every training setting as an optional typed field, bounded as `--set` bounds it: the
    schema of `TrainOptions.config` (so that OpenAPI shows each one)."""
    from .train.settings import schema, setting_type

    parts: dict[str, dict] = {"": {}, "model": {}, "densify": {}}
    for key, (_, default) in schema().items():
        part, _, name = key.rpartition(".")
        kind: Any = Annotated[setting_type(key), AfterValidator(partial(_checked, key))]
        parts[part][name] = (kind | None, Field(None, description=f"default {default!r}"))
    model = create_model("ModelSettings", __base__=JobOptions, **parts["model"])  # type: ignore[call-overload]
    densify = create_model("DensifySettings", __base__=JobOptions, **parts["densify"])  # type: ignore[call-overload]
    nested: Any = {"model": (model | None, None), "densify": (densify | None, None)}
    return create_model("TrainingSettings", __base__=JobOptions, **nested, **parts[""])  # type: ignore[call-overload]


def _train_options() -> type[TrainOptionsBase]:
    from .train.settings import NAMED

    settings = _training_settings()
    return create_model(
        "TrainOptions",
        __base__=TrainOptionsBase,  # type: ignore[call-overload]
        config=(settings | None, Field(None, description=TrainOptionsBase.model_fields["config"].description)),
        **{name: _named_field(name) for name in NAMED},
    )


# The preset, ablations, settings, and one typed field per setting offered by name.
TrainOptions = _train_options()


def first_error(exc) -> str:
    """A pydantic ValidationError as one line naming the field: `size: Input should be ...`."""
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    return f"{where}: {msg}" if where else msg
