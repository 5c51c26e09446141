"""Benchmark one JPGM update (the inner step of a self-estimation event) against the paper's 0.6 s.

One update regenerates the PSF stack from (c_j, b_v, s_v), rebuilds the OTFs, projects the
current volume, evaluates the data loss and back-propagates to the JPGM parameters, then takes
an Adam step: what ``time/jpgm_iter_ms`` logs. Measured for the matrix-Fourier fast path and
the angular-spectrum reference on the same inputs (their PSF stacks are compared too), at the
paper's size (20x/0.45, 101 depths, 161 px crops, 300 x 300 views, all 17 Zernike terms and the
shifts estimated) and at the small CPU size (small system, 31 depths, 64 x 64 views, ASM only:
the small system's crosstalk needs it). On a GPU the paper-size figure is compared with the
paper's 0.6 s per update (Note S3.5.2).

    python benchmarks/jpgm_update.py [--quick] [--repeats 3]
        [--out benchmarks/results/jpgm_update.json]
"""

from __future__ import annotations

import torch
from common import parser, timed, write_json

from fgat.devices import resolve_device
from fgat.losses import pixel_loss
from fgat.optics.operator import FLFMOperator
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system, parse_depths
from fgat.phantoms import beads
from fgat.simulation import sample_aberrations

PAPER_UPDATE_S = 0.6


def update_case(
    system_name: str,
    depths: str,
    view_size: int,
    methods: tuple[str, ...],
    device: torch.device,
    repeats: int,
) -> list[dict]:
    system = load_system(system_name)
    depths_um = parse_depths(depths)
    optics = sample_aberrations(
        system.n_lenslets,
        amplitude=0.1 if system_name == "small" else 1.0,
        intercept_range=1.0,
        slope_range=1.0,
        seed=0,
    )
    volume = torch.from_numpy(
        beads((len(depths_um), view_size, view_size), 40, sigma=1.0, seed=0)
    ).to(device)
    with torch.no_grad():
        truth = OpticsSpec(system, tuple(depths_um), **optics).jpgm(device=device)()
    measurement = FLFMOperator(truth, tuple(volume.shape)).forward(volume)
    rows, stacks = [], {}
    for method in methods:
        jpgm = OpticsSpec(system, tuple(depths_um)).jpgm(method=method, device=device)
        optimizer = torch.optim.Adam(jpgm.parameters(), lr=1e-3)

        def update():
            optimizer.zero_grad(set_to_none=True)
            loss = pixel_loss(
                FLFMOperator(jpgm(), tuple(volume.shape)).forward(volume), measurement, 1
            )
            loss.backward()
            optimizer.step()

        seconds = timed(update, repeats, device)
        with torch.no_grad():
            stacks[method] = jpgm()
            psf_s = timed(jpgm, repeats, device)
        rows.append(
            {
                "case": f"{system_name}, {len(depths_um)} depths, {view_size}^2 views",
                "method": method,
                "device": str(device),
                "update_s": seconds,
                "psf_s": psf_s,
                "vs_paper": PAPER_UPDATE_S / seconds,
            }
        )
    if len(stacks) == 2:
        fast, reference = stacks["mft"], stacks["asm"]
        error = float((fast - reference).norm() / reference.norm())
        for row in rows:
            row["mft_vs_asm_rel_l2"] = error
            row["speedup_vs_asm"] = rows[-1]["update_s"] / row["update_s"]
    return rows


def main() -> None:
    args = parser(
        __doc__, "benchmarks/results/jpgm_update.json", "small CPU case only"
    ).parse_args()
    device = resolve_device("auto")
    rows = update_case("small", "-22.5:22.5:31", 64, ("asm",), device, args.repeats)
    if not args.quick:
        rows += update_case("20x/0.45", "-75:75:101", 300, ("mft", "asm"), device, args.repeats)
    print(
        f"{'case':<38} {'method':>6} {'update (s)':>11} {'PSF (s)':>8} "
        f"{'0.6 s / update':>15} {'vs ASM':>7}"
    )
    for row in rows:
        print(
            f"{row['case']:<38} {row['method']:>6} {row['update_s']:>11.3f} {row['psf_s']:>8.3f} "
            f"{row['vs_paper']:>15.2f} {row.get('speedup_vs_asm', float('nan')):>7.2f}"
        )
    if any("mft_vs_asm_rel_l2" in row for row in rows):
        print(f"fast path vs ASM PSF stack, relative L2: {rows[-1]['mft_vs_asm_rel_l2']:.2e}")
    write_json(args.out, {"device": str(device), "rows": rows})


if __name__ == "__main__":
    main()
