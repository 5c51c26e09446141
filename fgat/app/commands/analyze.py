"""``fgat analyze``: the command family of the analyses (cross-information tables, tubule
widths, 3D cytometry, tracking).
"""

from __future__ import annotations

from fgat.app.arguments import add_device, add_output_folder, measured_centers


def add_analyze(subparsers) -> None:
    parser = subparsers.add_parser(
        "analyze",
        help="analyses: crossinfo (Note S5), fwhm, cytometry, track",
        description="Analyses of fgat's models and results; 'python -m fgat analyze crossinfo "
        "--help' lists the options of one.",
    )
    analyses = parser.add_subparsers(title="analyses", dest="analysis", required=True)
    crossinfo = analyses.add_parser(
        "crossinfo",
        help="Zernike/shift cross-information of JPGM (Note S5)",
        description="The cross-information between JPGM's Zernike coefficients and lenslet "
        "shifts with the volume held fixed (Note S4), and the three experiments of Note S5 at "
        "one optics point: the modal profiles of C_b and C_s (Tables S2-S3), the shift-"
        "injection leakage test against -A^-1 C dTheta_G (Table S4) and noisy joint refits "
        "against the inverse-Hessian standard errors (Table S5). The point is the true optics "
        "of the --config scene, or with --run the optics and volume a static fit estimated "
        "(its results folder: optics.yaml, psf.ome.tif, volume.ome.tif; the system is the "
        "config's scene.system, the lenslet centres the system's nominal ones or --centers, "
        "checked against psf.ome.tif). "
        "Writes the tables as CSV and markdown, eta_profiles.png, cross_information.png, "
        "leakage.png, summary.json, summary.md and config.yaml to OUT.",
    )
    crossinfo.add_argument(
        "--config", required=True, help="analysis YAML (see configs/crossinfo.yaml)"
    )
    add_output_folder(
        crossinfo, "write into a non-empty OUT, replacing only the analysis's own files there"
    )
    crossinfo.add_argument(
        "--run",
        dest="run_folder",
        metavar="RESULTS",
        help="a static fit's results folder (<root>/results/<run>, written with JPGM "
        "self-estimation): analyse its estimated optics and volume instead of the config's scene",
    )
    crossinfo.add_argument(
        "--centers",
        metavar="FILE|CALIBRATION",
        help="with --run: the lenslet centres the fit used (a centres CSV/.mat, or a folder "
        "written by fgat calibrate; default the system's nominal lattice, a phantom's)",
    )
    add_device(crossinfo)
    crossinfo.set_defaults(run=_run_crossinfo)
    from fgat.app.commands.analyses import add_analyses  # imported when used: keeps start-up fast

    add_analyses(analyses)


def _run_crossinfo(args) -> int:
    from tqdm import tqdm  # loaded when used: keeps start-up fast

    from fgat._core.devices import resolve_device  # imported when used: keeps start-up fast
    from fgat.app.crossinfo_tables import (  # imported when used: keeps start-up fast
        CrossInfoConfig,
        analyse,
        analysis_scene,
        check_analysis_memory,
        check_report_folder,
        run_scene,
        write_report,
    )
    from fgat.optics.systems import load_system  # imported when used: keeps start-up fast

    config = CrossInfoConfig.from_yaml(args.config)
    if args.centers is not None and args.run_folder is None:
        raise ValueError("--centers needs --run (the centres of a fit's lenslets)")
    out = check_report_folder(args.out, overwrite=args.overwrite)
    device = resolve_device(args.device)
    scene = config.simulation()
    if args.run_folder is None:
        jpgm, volume = analysis_scene(
            scene, crop_radius_px=config.crop_radius_px, method=config.method, device=device
        )
        operator, source = None, f"the scene of {args.config} at its true optics"
    else:
        system, centers = load_system(scene.system), None
        if args.centers is not None:
            centers, system = measured_centers(args.centers, system)
        jpgm, volume, operator = run_scene(
            args.run_folder,
            system,
            centers_px=centers,
            method=config.method,
            device=device,
        )
        source = f"the optics and volume of the static fit {args.run_folder}"
    check_analysis_memory(tuple(volume.shape), jpgm.n_views, jpgm.radius, jpgm=jpgm, device=device)
    n_pupil, n_views = len(jpgm.zernike_indices), jpgm.n_views
    print(
        f"{source}: system {jpgm.system.name}, {n_views} views, volume "
        f"{tuple(volume.shape)} (Z, Y, X), {n_pupil} Zernike terms; Jacobian of "
        f"{n_pupil + 4 * n_views} columns, 3 leakage refits, {config.refits} noisy joint refits"
    )
    with tqdm(total=4 + config.refits, desc="Jacobian", unit="step") as bar:

        def progress(stage: str, k: int) -> None:  # after the Jacobian, 3 leakage cases, refits
            leakage_done = stage == "refit" or (stage == "leakage" and k == 2)
            bar.set_description("noisy refits" if leakage_done else "leakage refits")
            bar.update(1)

        report = analyse(jpgm, volume, config, operator=operator, callback=progress)
    write_report(
        report,
        out,
        config,
        title=f"{jpgm.system.name}, {n_views} views, {jpgm.n_depths} depths",
        extra={"source": source, "system": jpgm.system.name, "volume_shape": list(volume.shape)},
    )
    summary = report.summary()
    profile, leakage, noisy = (
        summary["intercept_profile"],
        summary["leakage"],
        summary["repeatability"],
    )
    print(
        f"||C_s||_F / ||C_b||_F = {profile['frobenius_ratio_s_over_b']:.4f}; eta_11^b = "
        f"{profile.get('eta_b_11', float('nan')):.4f} (median eta^b "
        f"{profile['median_eta_b']:.4f})"
    )
    for case in leakage["cases"]:
        print(
            f"leakage {case['case']}: ||dTheta_G|| {case['delta_geometry_norm_px']:.4f} px, "
            f"measured {case['measured_norm_waves']:.3e} waves, predicted "
            f"{case['predicted_norm_waves']:.3e}, ratio {case['ratio']:.3f}, cosine "
            f"{case['cosine']:.3f}"
        )
    print(
        f"{noisy['refits']} noisy refits (sigma {noisy['noise_sigma']:.3g}): ||dTheta_P|| = "
        f"({noisy['pupil_norm_mean_waves']:.3e} +/- {noisy['pupil_norm_sd_waves']:.3e}) waves, "
        f"||dTheta_G|| = ({noisy['geometry_norm_mean_px']:.3e} +/- "
        f"{noisy['geometry_norm_sd_px']:.3e}) px; s.d. of j = 11 "
        f"{noisy.get('empirical_sd_11_waves', float('nan')):.3e} waves (predicted "
        f"{noisy.get('predicted_sd_11_waves', float('nan')):.3e}), median s.d. "
        f"{noisy['median_empirical_sd_waves']:.3e}"
    )
    if report.on_pixel_grid > 0.1:
        print(
            f"note: {report.on_pixel_grid:.0%} of the crop-centre coordinates c_v + b_v + s_v xi "
            "lie within 0.01 px of the pixel grid, where the bilinear crops (Eq. S12) have a "
            "kink: the Jacobian in the shifts is one-sided there, and the leakage map holds "
            "only for shifts to one side"
        )
    print(f"tables, figures and summary -> {out}")
    return 0
