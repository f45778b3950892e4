"""Readable figures of a table (usdfiber.table_plot, `usdfiber table plot --figure`)."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401
from usdfiber import table_plot
from usdfiber.cli import main


@pytest.fixture(scope="module")
def table_file(circle_table, tmp_path_factory):
    path = tmp_path_factory.mktemp("plot") / "circle.npz"
    circle_table.save(path)
    return path


def _png(path):
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    return buf.spec(), np.asarray(buf.get_pixels(oiio.FLOAT))


def test_longitudinal_curves_peak_on_the_cone_and_integrate_to_the_albedo(circle_table):
    thetas = (-60.0, -30.0, 0.0, 30.0)
    sigma = [0.05, 0.2, 0.5]
    fig = table_plot.longitudinal_curves(circle_table, sigma, theta_i=thetas)
    lines = [ln for ln in fig.axes[0].get_lines() if len(ln.get_xdata()) > 2]
    assert len(lines) == len(thetas)
    res = circle_table.grid.resolution_deg
    rec = circle_table.recolour(sigma)
    for ti, ln in zip(thetas, lines):
        x, m = np.asarray(ln.get_xdata()), np.asarray(ln.get_ydata())
        # A smooth round fiber scatters into the specular cone theta_o = -theta_i.
        assert abs(x[np.argmax(m)] + ti) <= 1.5 * res
        # int M dtheta_o = Lambda (p integrates to 1 over the sphere): luminance of the albedo.
        total = m.sum() * math.radians(180.0 / len(m))
        lum = float(rec.albedo_at(math.radians(ti), 0.0) @ [0.2126, 0.7152, 0.0722])
        assert total == pytest.approx(lum, rel=0.01)
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_cli_figures(table_file, tmp_path, capsys):
    grid = tmp_path / "grid.png"
    assert main(["table", "plot", str(table_file), "--figure", "grid", "--theta-i", "-45", "0", "--psi", "0", "90",
                 "--phi-i", "0", "--mu-a", "0.01", "0.05", "0.1", "-o", str(grid)]) == 0
    spec, px = _png(grid)
    assert spec.width > 600 and spec.height > 300         # a figure with axes, not 72 rows of bins
    assert px[..., :3].std() > 0.1                          # not blank
    for fig in ("longitudinal", "errors"):
        out = tmp_path / f"{fig}.png"
        assert main(["table", "plot", str(table_file), "--figure", fig, "--theta-i", "0", "30", "--phi-i", "0",
                     "-o", str(out)]) == 0
        spec, px = _png(out)
        assert spec.width > 400 and px[..., :3].std() > 0.05
    capsys.readouterr()
    assert main(["table", "plot", str(table_file), "--figure", "grid", "--theta-i", "0", "--phi-i", "0",
                 "-o", str(tmp_path / "x.unknown")]) == 2
    err = capsys.readouterr().err
    assert "x.unknown" in err and err.count("\n") == 1
    assert main(["table", "plot", str(table_file), "--figure", "grid", "--theta-i", "100", "--phi-i", "0",
                 "-o", str(grid)]) == 2
    assert "within [-90, 90]" in capsys.readouterr().err


def test_fit_figure_shows_the_table_and_each_model(circle_table):
    """Figure 12-style: per row the table's rotation-averaged scattering on the specular cone
    and each fitted model's, labelled with the fit's error over the sphere."""
    from usdfiber.fit import FitTarget, fit_tables

    sigma = [0.05, 0.2, 0.5]
    fig = table_plot.fit_comparison([circle_table], sigma, theta_i=(-30.0, 0.0))
    axes = fig.axes
    assert len(axes) == 4                                   # 2 rows x (azimuthal, longitudinal)
    target = FitTarget.from_tables([circle_table], sigma)
    lum = target.values @ np.array([0.2126, 0.7152, 0.0722])
    i = int(np.argmin(np.abs(np.degrees(target.theta_i) - 0.0)))
    longitudinal = axes[3].get_lines()
    labels = [ln.get_label() for ln in longitudinal]
    assert labels[0] == "table" and labels[1].startswith("chiang (rel L2") and labels[2].startswith("khungurn")
    # the table's longitudinal curve is the target integrated over dphi
    np.testing.assert_allclose(longitudinal[0].get_ydata(), np.maximum(lum[i].sum(axis=1) * target.dphi_step, 1e-9))
    err = fit_tables([circle_table], "chiang", sigma_a=sigma, cache=False).error["rel_l2"]
    assert f"{float(np.asarray(err) @ [0.2126, 0.7152, 0.0722]):.2f}" in labels[1]
    # a round fiber's fitted Chiang model follows its table: the longitudinal curves agree
    # within a factor of 2 wherever the table holds 1 % of its peak or more
    t, c = longitudinal[0].get_ydata(), longitudinal[1].get_ydata()
    big = t > 0.01 * t.max()
    assert np.all(np.abs(np.log(c[big] / t[big])) < math.log(2.0))
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_cli_grid_is_the_default_and_slice_on_request(table_file, tmp_path, capsys):
    out = tmp_path / "default.png"
    assert main(["table", "plot", str(table_file), "-o", str(out)]) == 0
    spec, _ = _png(out)
    assert spec.width > 600 and spec.height > 300 and "(grid)" in capsys.readouterr().out
    sl = tmp_path / "slice.png"
    assert main(["table", "plot", str(table_file), "--figure", "slice", "--theta-i", "-30", "-o", str(sl)]) == 0
    spec, _ = _png(sl)
    assert (spec.width, spec.height) == (36 * 4, 18 * 4)     # 10 degree bins, 4 pixels each
    capsys.readouterr()
    assert main(["table", "plot", str(table_file), "--figure", "slice", "-o", str(sl)]) == 2
    assert "--figure slice needs --theta-i" in capsys.readouterr().err
    fit = tmp_path / "fit.png"
    assert main(["table", "plot", str(table_file), "--figure", "fit", "--theta-i", "0", "-o", str(fit)]) == 0
    spec, px = _png(fit)
    assert spec.width > 600 and px[..., :3].std() > 0.05


def test_cli_output_directory_and_names_without_a_format(table_file, tmp_path, capsys):
    """-o an existing directory writes FILE's name with the figure in it (it wrote DIR.png beside
    it); a name without an extension is refused before any work (matplotlib added .png)."""
    out = tmp_path / "figures"
    out.mkdir()
    assert main(["table", "plot", str(table_file), "-o", str(out)]) == 0
    assert main(["table", "plot", str(table_file), "--figure", "slice", "--theta-i", "0", "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["circle-grid.png", "circle-slice.png"]
    assert not (tmp_path / "figures.png").exists()
    assert f"wrote {out / 'circle-grid.png'} (grid)" in capsys.readouterr().out
    assert main(["table", "plot", str(table_file), "-o", str(tmp_path / "figure")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no extension to choose the image format by" in err
    assert not list(tmp_path.glob("figure.*"))


@pytest.mark.parametrize("decades", ["400", "0", "-1", "nan"])
def test_cli_decades_out_of_range_is_a_usage_error(table_file, tmp_path, capsys, decades):
    with pytest.raises(SystemExit) as e:
        main(["table", "plot", str(table_file), "--decades", decades, "-o", str(tmp_path / "g.png")])
    assert e.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--decades" in last and "Traceback" not in last and not (tmp_path / "g.png").exists()
