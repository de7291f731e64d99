"""Shape from shading from Python (`photostereo.sfs`): rendered spheres under a distant light
with the light given and estimated, a reflectance other than Lambert's, a plane through a
pinhole camera under a light at its centre (closed form), and refusals that name what is
wrong. The bounds are those of the command's tests (`cli/tests/sfs.rs`)."""

import warnings

import numpy as np
import pytest

import photostereo as ps

SIZE = 96
ALBEDO = 0.8


def slanted(slant_deg, azimuth_deg):
    s, a = np.radians(slant_deg), np.radians(azimuth_deg)
    return np.array([np.sin(s) * np.cos(a), np.sin(s) * np.sin(a), np.cos(s)])


LIGHT = slanted(30.0, 40.0)


def mean_angle(normals, truth, mask):
    cos = np.clip(np.sum(normals[mask] * truth[mask], axis=1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


@pytest.fixture(scope="module")
def sphere():
    return ps.render("sphere", SIZE, LIGHT[None, :], albedo=ALBEDO)


def test_a_sphere_under_an_oblique_light(sphere):
    r = ps.sfs(sphere["images"][0], sphere["mask"], light=LIGHT, albedo=ALBEDO)
    m = sphere["mask"]
    assert r["method"] == "horn" and r["report"]["converged"]
    assert np.isfinite(r["normals"][m]).all() and np.isnan(r["depth"][~m]).all()
    err = mean_angle(r["normals"], sphere["normals"], m)
    print(f"horn, light given: {err:.2f}° in {r['report']['iterations']} iterations")
    assert err < 2.0
    # Height up to an offset, against the true height's range.
    d, t = r["depth"][m], sphere["depth"][m]
    rmse = np.sqrt(np.mean(((d - d.mean()) - (t - t.mean())) ** 2))
    assert rmse < 0.05 * (t.max() - t.min())
    assert r["light_source"] == "given" and r["albedo_source"] == "given"


def test_horn_tells_a_cut_outline_from_a_silhouette(sphere):
    # The report's "occluding" is the outline tested against the image before the solve: the
    # sphere's silhouette contradicts an occluding contour nowhere; the vase's cut ends, which
    # face the camera, do, and the solve warns (as the command does).
    r = ps.sfs(sphere["images"][0], sphere["mask"], light=LIGHT, albedo=ALBEDO)
    test = r["report"]["occluding"]
    assert test["pixels"] > 100 and test["contradicted"] == 0
    assert not any("not an occluding contour" in w for w in r["warnings"])
    vase = ps.render("vase", SIZE, LIGHT[None, :], albedo=ALBEDO)
    with pytest.warns(ps.PhotostereoWarning, match="not an occluding contour"):
        r = ps.sfs(vase["images"][0], vase["mask"], light=LIGHT, albedo=ALBEDO)
    test = r["report"]["occluding"]
    print(f"vase: {test['contradicted']} of {test['pixels']} outline pixels contradicted")
    assert test["fraction"] > 0.05


def test_horn_coarse_to_fine_can_be_turned_off():
    # 192 px: the sphere keeps over 3000 pixels at half resolution, so by default Horn solves
    # it there first; coarse_to_fine=False solves at full resolution only. Both are accurate.
    big = ps.render("sphere", 192, LIGHT[None, :], albedo=ALBEDO)
    m = big["mask"]
    runs = {
        c2f: ps.sfs(big["images"][0], m, light=LIGHT, albedo=ALBEDO, coarse_to_fine=c2f)
        for c2f in (True, False)
    }
    for c2f, r in runs.items():
        err = mean_angle(r["normals"], big["normals"], m)
        print(f"coarse to fine {c2f}: {err:.2f}°, {r['report']['iterations']} iterations after "
              f"{r['report']['coarse_iterations']}")
        assert r["report"]["converged"] and err < 2.0
    assert runs[True]["report"]["coarse_iterations"] > 0
    assert runs[False]["report"]["coarse_iterations"] == 0


def test_light_and_albedo_are_estimated_when_not_given(sphere):
    r = ps.sfs(sphere["images"][0], sphere["mask"])
    assert r["light_source"] == "estimated" and r["albedo_source"] == "estimated"
    light = np.asarray(r["light"]) / np.linalg.norm(r["light"])
    off = np.degrees(np.arccos(np.clip(light @ LIGHT, -1.0, 1.0)))
    print(f"estimated light {off:.2f}° off, albedo {r['albedo']:.4f}")
    assert off < 3.0 and abs(r["albedo"] - ALBEDO) / ALBEDO < 0.03
    assert r["estimate"]["slant_deg"] == pytest.approx(np.degrees(np.arccos(light[2])), abs=1e-6)
    assert mean_angle(r["normals"], sphere["normals"], sphere["mask"]) < 3.0


def test_the_reflectance_is_the_one_given():
    on = ps.render("sphere", SIZE, LIGHT[None, :], albedo=ALBEDO, material="oren-nayar")
    m = on["mask"]
    right = ps.sfs(on["images"][0], m, light=LIGHT, albedo=ALBEDO, material="oren-nayar")
    lambert = ps.sfs(on["images"][0], m, light=LIGHT, albedo=ALBEDO)
    a = mean_angle(right["normals"], on["normals"], m)
    b = mean_angle(lambert["normals"], on["normals"], m)
    print(f"Oren-Nayar sphere: {a:.2f}° with its reflectance, {b:.2f}° assuming Lambert's")
    assert a < 2.0 and a < 0.5 * b


def test_horn_warns_when_its_outline_contradicts_the_occluding_boundary():
    # Rough spheres at 64² and 96²: at 64² Horn settles on a surface that explains the image as
    # well as the right one but turns the normals beside the outline away from it
    # (cli/tests/sfs.rs, which also asserts that both cases occur). The warning reaches Python
    # as a PhotostereoWarning exactly when the report's outline is misaligned, and it is never
    # a false alarm. The outline repair, which solves the 64² one (next test), is turned off:
    # this is the check's own path.
    params = {"sigma": 0.4}
    seen = []
    for size in (64, 96):
        sc = ps.render("sphere", size, LIGHT[None, :], albedo=ALBEDO, material="oren-nayar",
                       material_params=params)
        m = sc["mask"]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            r = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, material="oren-nayar",
                       material_params=params, outline_repair=False)
        assert r["report"]["outline_repair"] is None
        outline = r["report"]["outline"]
        err = mean_angle(r["normals"], sc["normals"], m)
        warned = any(issubclass(w.category, ps.PhotostereoWarning)
                     and "contradicts the occluding boundary" in str(w.message) for w in caught)
        print(f"rough sphere {size}²: {err:.1f}°, {100 * outline['misaligned_fraction']:.0f}% of "
              f"{outline['pixels']} outline pixels misaligned, warned {warned}")
        assert warned == (outline["misaligned_fraction"] > 0.25)
        assert warned == any("occluding boundary" in w for w in r["warnings"])
        assert err > 12.0 if warned else err < 6.0
        seen.append(warned)
    assert seen == [True, False]


def test_horn_repairs_a_result_that_contradicts_its_outline():
    # The same rough sphere at 64²: the first solve contradicts the occluding boundary, so it
    # is solved again upsampled 2x, and that result, which honours the boundary, is returned
    # without the warning; outline_repair=False returns the first one, warned.
    params = {"sigma": 0.4}
    sc = ps.render("sphere", 64, LIGHT[None, :], albedo=ALBEDO, material="oren-nayar",
                   material_params=params)
    m = sc["mask"]
    kw = dict(light=LIGHT, albedo=ALBEDO, material="oren-nayar", material_params=params)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = ps.sfs(sc["images"][0], m, outline_repair=False, **kw)
        repaired = ps.sfs(sc["images"][0], m, **kw)
    e_first = mean_angle(first["normals"], sc["normals"], m)
    e = mean_angle(repaired["normals"], sc["normals"], m)
    repair = repaired["report"]["outline_repair"]
    print(f"rough sphere 64²: first {e_first:.1f}°, repaired {e:.1f}°, {repair}")
    assert repair["kept"] and repair["converged"]
    assert repair["first"]["misaligned_fraction"] > 0.25
    assert repair["first"] == first["report"]["outline"]
    assert repair["upsampled"]["misaligned_fraction"] <= 0.25
    assert repaired["report"]["outline"]["misaligned_fraction"] <= 0.25
    assert e_first > 12.0 and e < 6.0
    assert not any("occluding boundary" in w for w in repaired["warnings"])
    assert any("outline repair" in a for a in repaired["report"]["assumptions"])
    assert sum("contradicts the occluding boundary" in str(w.message) for w in caught) == 1
    with pytest.raises(ValueError, match="outline_repair"):
        ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, method="tsai-shah",
               outline_repair=False)


def test_horn_repeats_its_continuation_where_that_lowers_the_energy():
    # A bust at 128² under the 30° light: repeating the continuation from its own result (the
    # default) ends much nearer the truth than one continuation (restarts=False), and the report
    # counts the repeats kept.
    sc = ps.render("bust", 128, LIGHT[None, :], albedo=ALBEDO)
    m = sc["mask"]
    once = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, restarts=False)
    repeated = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO)
    e_once = mean_angle(once["normals"], sc["normals"], m)
    e = mean_angle(repeated["normals"], sc["normals"], m)
    print(f"bust 128², 30°: once {e_once:.2f}°, repeated {repeated['report']['restarts']} "
          f"times {e:.2f}°")
    assert once["report"]["restarts"] == 0
    assert repeated["report"]["restarts"] > 0 and repeated["report"]["converged"]
    assert e < e_once - 1.5
    with pytest.raises(ValueError, match="restarts"):
        ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, method="tsai-shah",
               restarts=False)


def test_horn_refines_a_given_start_surface():
    # The frame-filling relief at 128² under the 30° light: from its default start Horn ends
    # in another minimum of its energy; from the true heights averaged over 7 x 7 pixels (what
    # a depth sensor or a coarse reconstruction gives) it returns normals nearer the truth than
    # the start's, with no continuation, coarse level or repeat.
    sc = ps.render("relief", 128, LIGHT[None, :], albedo=ALBEDO)
    m = sc["mask"]
    depth = np.where(m, sc["depth"], 0.0)
    from numpy.lib.stride_tricks import sliding_window_view as windows
    pad = lambda a: np.pad(a, 3)
    start = windows(pad(depth), (7, 7)).sum(axis=(2, 3)) / windows(pad(m * 1.0), (7, 7)).sum(
        axis=(2, 3))
    start = np.where(m, start, np.nan)
    refined = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, start=start)
    default = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO)
    gy, gx = np.gradient(start)
    start_normals = np.dstack([-gx, gy, np.ones_like(gx)])
    start_normals /= np.linalg.norm(start_normals, axis=2, keepdims=True)
    e_start = mean_angle(start_normals, sc["normals"], m)
    e = mean_angle(refined["normals"], sc["normals"], m)
    e_default = mean_angle(default["normals"], sc["normals"], m)
    print(f"relief 128², 30°: start {e_start:.2f}°, refined {e:.2f}°, default {e_default:.2f}°")
    assert refined["report"]["restarts"] == 0 and refined["report"]["coarse_iterations"] == 0
    assert refined["report"]["converged"]
    assert e < 0.75 * e_start and e < e_default / 4
    assert refined["start_scale"] == 1.0 and refined["start_filled"] == 0
    assert default["start_scale"] is None
    # One row short is not the image's view at another resolution.
    with pytest.raises(ValueError, match="a crop or a padding"):
        ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, start=start[:-1])
    with pytest.raises(ValueError, match="start"):
        ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, start=start, method="tsai-shah")
    with pytest.raises(ValueError, match="nothing to fill them from"):
        ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, start=np.full((32, 32), np.nan))


def test_horn_refines_a_coarse_start_with_holes():
    # A depth sensor's view of the relief: a quarter of the image's resolution (4 x 4 block
    # means, in the sensor's pixels), with one reading in ten missing. It is resampled to the
    # image's grid, filled and refined, ending far nearer the truth than Horn's default.
    sc = ps.render("relief", 128, LIGHT[None, :], albedo=ALBEDO)
    m = sc["mask"]
    assert m.all()  # frame-filling: every sensor reading is on the object
    blocks = sc["depth"].reshape(32, 4, 32, 4).mean(axis=(1, 3)) / 4
    i, j = np.mgrid[0:32, 0:32]
    coarse = np.where((i * 13 + j * 7) % 10 == 0, np.nan, blocks)
    refined = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO, start=coarse)
    default = ps.sfs(sc["images"][0], m, light=LIGHT, albedo=ALBEDO)
    e = mean_angle(refined["normals"], sc["normals"], m)
    e_default = mean_angle(default["normals"], sc["normals"], m)
    print(f"relief 128², 30°, start at 32² with {refined['start_filled']} readings missing: "
          f"refined {e:.2f}°, default {e_default:.2f}°")
    assert refined["start_scale"] == 4.0
    assert refined["start_filled"] == int(np.isnan(coarse).sum())
    assert refined["report"]["converged"]
    assert e < e_default / 4


def test_a_plane_through_a_pinhole_under_a_light_at_its_centre():
    # A plane facing the camera at depth Z0, the light at the camera centre: a pixel's ray
    # meets it at distance r = Z0 sqrt(1 + x² + y²) (x, y normalised), where cos θ = Z0 / r
    # and the fall-off is 1/r², so I = ρ Φ Z0 / r³.
    n, f, z0, phi = 64, 80.0, 100.0, 1.0e4
    k = np.array([[f, 0.0, (n - 1) / 2], [0.0, f, (n - 1) / 2], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:n, 0:n]
    r = z0 * np.sqrt(1 + ((u - k[0, 2]) / f) ** 2 + ((v - k[1, 2]) / f) ** 2)
    image = (phi * z0 / r**3).astype(np.float32)
    out = ps.sfs(
        image,
        np.ones((n, n), bool),
        camera=k,
        light_position=(0, 0, 0),
        light_intensity=phi,
        albedo=1.0,
    )
    assert out["method"] == "perspective" and out["warnings"] == []
    assert out["start_scale"] is None and out["start_filled"] is None
    # The mask fills the image: no outline inside it to judge.
    assert out["report"]["outline"] is None
    depth_err = np.abs(out["depth"] - z0).max() / z0
    tilt = np.degrees(np.arccos(np.clip(out["normals"][..., 2], -1.0, 1.0))).max()
    print(f"plane: depth within {depth_err:.1e} of Z0, normals within {tilt:.3f}°")
    assert depth_err < 1e-4 and tilt < 0.01
    # Without the intensity and albedo, 1 is assumed, and a warning says so.
    with pytest.warns(ps.PhotostereoWarning, match="1 assumed"):
        r = ps.sfs(image, np.ones((n, n), bool), camera=k, light_position=(0, 0, 0))
    assert r["albedo_source"] == "assumed"


def test_a_sphere_through_a_pinhole_honours_its_outline():
    # A sphere of radius R centred on the optical axis at distance D, the light at the camera
    # centre, in closed form: a pixel's ray d = ((u - cx)/f, -(v - cy)/f, -1) (x right, y up, z
    # to the viewer) meets it at the depth t of the nearer root of |t d - C|² = R², where the
    # normal is (t d - C)/R, cos θ = n·(-d/|d|) and the fall-off 1/(t|d|)².
    n, f, big_d, radius, phi = 64, 80.0, 100.0, 30.0, 1.0e4
    k = np.array([[f, 0.0, (n - 1) / 2], [0.0, f, (n - 1) / 2], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:n, 0:n]
    d = np.stack([(u - k[0, 2]) / f, -(v - k[1, 2]) / f, -np.ones((n, n))], axis=-1)
    c = np.array([0.0, 0.0, -big_d])
    a, b = np.sum(d * d, axis=-1), -2.0 * (d @ c)
    disc = b * b - 4.0 * a * (c @ c - radius**2)
    mask = disc > 0.0
    t = np.where(mask, (-b - np.sqrt(np.where(mask, disc, 0.0))) / (2.0 * a), np.nan)
    normal = (t[..., None] * d - c) / radius
    cos = np.sum(normal * -d, axis=-1) / np.sqrt(a)
    image = np.where(mask, phi * np.clip(cos, 0.0, None) / (t * t * a), 0.0).astype(np.float32)
    out = ps.sfs(image, mask, camera=k, light_position=(0, 0, 0), light_intensity=phi,
                 albedo=1.0)
    err = mean_angle(out["normals"], normal, mask)
    depth_err = np.nanmax(np.abs(out["depth"] - t)[mask]) / big_d
    outline = out["report"]["outline"]
    print(f"sphere through a pinhole: normals {err:.2f}°, depth within {depth_err:.1e} of D; "
          f"outline {100 * outline['misaligned_fraction']:.0f}% of {outline['pixels']} misaligned")
    assert err < 5.0 and depth_err < 0.05
    # The perspective method takes the outline for an occluding contour and measures it, as
    # the command does (`outline` in report.json); a right result honours it and is not warned.
    assert outline["pixels"] > 0 and outline["misaligned_fraction"] <= 0.25
    assert not any("occluding boundary" in w for w in out["warnings"])
    # The outline is tested against the image too (`occluding`): a silhouette is no brighter
    # than a surface turning away from the view can be, at the depth the result gives it.
    occluding = out["report"]["occluding"]
    assert occluding["pixels"] > 0 and occluding["contradicted"] == 0


@pytest.mark.parametrize(
    "kwargs, error, words",
    [
        # The library's refusals name the parameter as `name`; the module's start with it.
        ({"method": "fast-marching", "light": LIGHT}, ps.Error, "`method`"),
        ({"method": "sketch"}, ValueError, "^method"),
        ({"material": "phong"}, ps.Error, "`light`"),
        ({"material": "phong", "light": LIGHT}, ps.Error, "`albedo`"),
        ({"material": "mirror", "light": LIGHT, "albedo": 1.0}, ps.Error, "`material`"),
        ({"method": "perspective", "light_position": (0, 0, 0)}, ValueError, "^camera"),
        ({"light": LIGHT, "camera": np.eye(3)}, ValueError, "^camera"),
        ({"light": LIGHT, "refine": False}, ValueError, "^refine"),
        (
            {"light_position": (0, 0, 0), "camera": np.eye(3), "refine": False,
             "refine_iterations": 3},
            ValueError,
            "^refine_iterations",
        ),
        ({"light_position": (0, 0, 0), "camera": np.eye(3), "smoothness": 0.1}, ValueError,
         "^smoothness"),
        ({"light": (1.0, 0.0)}, ValueError, "^light"),
        ({"light": LIGHT, "boundary": "open"}, ValueError, "^boundary"),
        ({"light": LIGHT, "transfer": "gamma"}, ValueError, "^transfer"),
        ({"light": LIGHT, "albedo": -1.0}, ps.Error, "`albedo`"),
        ({"method": "tsai-shah", "light": LIGHT, "coarse_to_fine": False}, ValueError,
         "^coarse_to_fine"),
    ],
)
def test_bad_input_is_named(sphere, kwargs, error, words):
    with pytest.raises(error, match=words):
        ps.sfs(sphere["images"][0], sphere["mask"], **kwargs)


def test_without_a_mask_the_object_is_found_and_a_warning_says_how(sphere):
    with pytest.warns(ps.PhotostereoWarning, match="no mask"):
        r = ps.sfs(sphere["images"][0], light=LIGHT, albedo=ALBEDO)
    lit = sphere["mask"] & (sphere["images"][0] > 0)
    assert r["mask"][lit].all() and not r["mask"][~sphere["mask"]].any()


def test_images_of_other_types_and_shapes(sphere):
    img = sphere["images"][0]
    run = lambda image, **kw: ps.sfs(image, sphere["mask"], light=LIGHT, albedo=ALBEDO, **kw)
    with pytest.raises(ValueError, match="one image"):
        ps.sfs(img[None])
    with pytest.raises(TypeError, match="image"):
        ps.sfs(img.tolist())
    # 16-bit codes are scaled to [0, 1]: the same solution as the floats they round.
    codes = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
    a = run(codes)
    assert np.array_equal(a["normals"], run(codes.astype(np.float32) / 65535)["normals"],
                          equal_nan=True)
    # Three channels are mixed to grey with BT.601's weights (summing to 1): a grey colour
    # image is its grey image, up to the rounding of the mix.
    colour = run(np.stack([img] * 3, axis=-1))["normals"]
    assert mean_angle(colour, run(img)["normals"], sphere["mask"]) < 0.01
    # 8-bit codes are decoded from sRGB unless the transfer says they are linear.
    srgb = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.clip(img, 0, 1) ** (1 / 2.4) - 0.055)
    eight = np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8)
    decoded = mean_angle(run(eight)["normals"], sphere["normals"], sphere["mask"])
    with pytest.warns(ps.PhotostereoWarning, match="brighter than the albedo"):
        linear = run(eight, transfer="linear")
    undecoded = mean_angle(linear["normals"], sphere["normals"], sphere["mask"])
    print(f"8-bit sRGB image: {decoded:.2f}° decoded, {undecoded:.2f}° read as linear")
    assert decoded < 2.0 < undecoded
