"""Generator configs: strict YAML -> dataclasses, one-line errors naming the file and the key."""

from __future__ import annotations

import pytest

from synth.camera import CameraConfig
from synth.config import GeneratorConfig, load_config


def test_empty_file_is_the_default_and_values_are_typed(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("")
    assert load_config(p) == GeneratorConfig()
    p.write_text("seed: 3\ncamera:\n  focal_mm: [35, 50]\n  rare_rate: 0\noutput: {shard_size: 8}\n")
    c = load_config(p)
    assert c.seed == 3 and c.output.shard_size == 8
    assert c.camera == CameraConfig(focal_mm=(35.0, 50.0), rare_rate=0.0)
    assert isinstance(c.camera.focal_mm[0], float)


@pytest.mark.parametrize(
    "text, message",
    [
        ("sede: 3\n", "sede: unknown key (known: background, camera, engine, garments, ground, hair, labels, num, occluders, output,"),
        ("camera:\n  focal: [1, 2]\n", "camera.focal: unknown key"),
        ("seed: three\n", "seed: expected an integer, got 'three'"),
        ("seed: true\n", "seed: expected an integer"),
        ("camera: {focal_mm: [35]}\n", "camera.focal_mm: expected 2 values, got 1"),
        ("camera: {rare_rate: .nan}\n", "camera.rare_rate: expected a finite number"),
        ("camera: {truncation_rate: 2}\n", "camera: camera truncation_rate must be in [0, 1]"),
        ("num: 0\n", "(top level): num (the number of images) must be positive"),
        ("num: 0\nposes: {source: library, library: m}\nsequence: {enabled: true}\n",
         "num (the number of sequences) must be positive"),
        ("camera: 3\n", "camera: expected a mapping"),
        ("[1, 2]\n", "(top level): expected a mapping"),
        ("seed: [\n", "not valid YAML"),
        ("subjects: {age: [10, 95]}\n", "subjects: subjects: age must be [low, high] years with 0 <= low <= high <= 90"),
        ("subjects: {age: [40, 20]}\n", "age must be [low, high]"),
        ("subjects: {children: 1.5}\n", "children must be a share in [0, 1]"),
        ("poses: {max_redraws: 0}\n", "poses.max_redraws must be in [1, 10000]"),
        ("poses: {child_clips: [a]}\n", "child_clips need source: library or mix"),
        ("camera: {height_m: [2, 1]}\n", "camera height_m must be [] or [low, high]"),
        ("camera: {f_number: [0.1, 2]}\n", "camera f_number must be [] or [low, high]"),
        ("camera: {frontal_rate: -0.5}\n", "camera frontal_rate must be in [0, 1]"),
        ("camera: {frontal_rate: 0.5}\nposes: {source: library, library: m}\nsequence: {enabled: true}\n",
         "camera.frontal_rate applies to single images"),
        ("ground: {samples: 0}\n", "ground.samples must be in [1, 1024]"),
        ("render: {sampler: sobol}\n", "render.sampler must be one of independent, stratified, multijitter"),
        ("render: {denoise_quality: best}\n", "render.denoise_quality must be high, balanced or fast"),
        ("hair: {styles: {short: -1}}\n", "hair.styles must be non-negative weights"),
        ("hair: {styles: {short: 0, long: 0, tied: 0, curly: 0}}\n", "hair.styles must be non-negative weights, not all 0"),
        ("hair: {styles: {mohawk: 1}}\n", "hair.styles.mohawk: unknown key"),
    ],
)
def test_bad_configs_are_one_line_errors_naming_file_and_key(tmp_path, text, message):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ValueError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg
    assert message in msg, msg
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "absent.yaml")


def test_overrides_set_dotted_keys_as_yaml_values(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("render: {spp: 49}\n")
    cfg = load_config(p, ["hair.enabled=false", "render.denoise=true", "subjects.age=[0, 90]", "camera.height_m=[]"])
    assert cfg.render.spp == 49 and cfg.render.denoise and not cfg.hair.enabled
    assert cfg.subjects.age == (0.0, 90.0) and cfg.camera.height_m == ()
    assert load_config("-", ["num=5"]).num == 5


@pytest.mark.parametrize(
    "override, message",
    [
        ("hair.enabled", "override 'hair.enabled' is not KEY=VALUE"),
        ("hair..enabled=1", "is not KEY=VALUE"),
        ("render.spp.x=1", "override render.spp.x: spp is not a section"),
        ("hair.colour=red", "with --set hair.colour=red: hair.colour: unknown key"),
        ("render.spp=[", "override render.spp: not a YAML value"),
    ],
)
def test_bad_overrides_are_one_line_errors(tmp_path, override, message):
    p = tmp_path / "c.yaml"
    p.write_text("render: {spp: 49}\n")
    with pytest.raises(ValueError) as exc:
        load_config(p, [override])
    assert message in str(exc.value) and str(p) in str(exc.value) and "\n" not in str(exc.value)


def test_default_yaml_writes_out_the_embedded_defaults():
    from pathlib import Path

    from synth.config import GeneratorConfig

    root = Path(__file__).resolve().parents[2]
    assert load_config(root / "configs" / "synth" / "default.yaml") == GeneratorConfig()


def test_sampler_spp_rules_are_mitsubas_and_a_rounded_spp_is_a_one_line_error(tmp_path):
    import mitsuba as mi

    from synth.config import SAMPLERS, RenderConfig, sampler_spp

    mi.set_variant("scalar_rgb")
    for sampler in SAMPLERS:
        for n in range(1, 70):
            assert sampler_spp(sampler, n) == mi.load_dict({"type": sampler, "sample_count": n}).sample_count(), (sampler, n)
    assert RenderConfig(sampler="ldsampler", spp=64).spp == 64
    with pytest.raises(ValueError, match=r"render.spp 36 with render.sampler ldsampler: Mitsuba would render 64 .*power of 4"):
        RenderConfig(sampler="ldsampler", spp=36)
    p = tmp_path / "c.yaml"
    p.write_text("render: {spp: 32}\n")  # the default sampler, multijitter, would render 5 x 7
    with pytest.raises(ValueError) as exc:
        load_config(p)
    assert "Mitsuba would render 35" in str(exc.value) and str(p) in str(exc.value) and "\n" not in str(exc.value)
