import numpy as np
import pytest

from edgerecon.synth.textures import GENERATORS, build_texture, make_texture, periodic_noise


def test_periodic_noise_is_tileable_and_normalised():
    rng = np.random.default_rng(0)
    f = periodic_noise(rng, (64, 96))
    assert f.shape == (64, 96)
    assert abs(float(f.mean())) < 1e-5 and abs(float(f.std()) - 1) < 1e-4
    # The wrap-around step is as smooth as the steps inside the texture.
    inner = np.abs(np.diff(f, axis=1)).mean()
    wrap = np.abs(f[:, 0] - f[:, -1]).mean()
    assert wrap < 2 * inner


@pytest.mark.parametrize("kind", sorted(GENERATORS))
def test_every_kind_wraps_seamlessly(kind):
    texel = 1 / 64  # a power of two keeps the shifted coordinates exact in float32
    tex = make_texture(kind, 3, (128, 128), texel)
    assert tex.levels[0].shape == (128, 128, 3) and tex.levels[0].dtype == np.uint8
    assert len(tex.levels) >= 4
    assert tex.period_m == (2.0, 2.0)
    u = np.random.default_rng(1).uniform(0, 2, 500).astype(np.float32)
    v = np.random.default_rng(2).uniform(0, 2, 500).astype(np.float32)
    a = tex.sample(u, v, texel)
    b = tex.sample(u + 2, v - 4, texel)  # one period to the right, two up
    np.testing.assert_allclose(a, b, atol=1.01 / 255)  # remap rounds to whole grey levels
    # ... and it is not constant (every kind has some texture).
    assert a.std(axis=0).max() > 0.002


def test_sample_hits_texel_centres_exactly_and_filters_with_footprint():
    img = np.zeros((64, 64, 3), np.uint8)
    img[::2, :, :] = 200  # horizontal lines one texel thick
    tex = build_texture(img, texel_m=0.01)
    # Texel (row 4, col 7) covers u in [0.07, 0.08), v in [0.04, 0.05); its centre is exact.
    val = tex.sample(np.array([0.075], np.float32), np.array([0.045], np.float32), 0.01)
    np.testing.assert_allclose(val[0], 200 / 255, atol=1e-6)
    val = tex.sample(np.array([0.075], np.float32), np.array([0.055], np.float32), 0.01)
    np.testing.assert_allclose(val[0], 0.0, atol=1e-6)
    # Seen from far away (footprint 4 texels) the lines average out to grey.
    far = tex.sample(np.full(50, 0.3, np.float32), np.linspace(0, 0.5, 50, dtype=np.float32), 0.04)
    np.testing.assert_allclose(far, 100 / 255, atol=0.02)


def test_unknown_kind_and_bad_images_are_rejected():
    with pytest.raises(ValueError, match="unknown texture kind"):
        make_texture("velvet", 0, (64, 64), 0.01)
    with pytest.raises(ValueError, match="uint8"):
        build_texture(np.zeros((8, 8), np.float32), 0.01)  # type: ignore[arg-type]
