//! `glint bench fit`: speed against accuracy of the fit. A simulated tile (the rig's mock
//! lab, Blinn-Phong with known kd, ks, n) is captured, merged and calibrated once; then
//! each sampling strategy at each sample count is fitted (every candidate model, one
//! core) and timed, and the fitted n and ks/kd are compared with the truth. Writes a CSV
//! and an SVG chart of fit time against parameter error.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use glint::fit::choose::choose;
use glint::fit::model::{Model, Reflectance};
use glint::fit::run::load_inputs;
use glint::fit::sample::{sample, SampleOptions, Strategy};
use glint::fit::solve::{fit, Options, Sample};
use glint::{capture, devices, rig};

#[derive(Args)]
pub struct FitBenchArgs {
    /// The rig whose simulated tile is captured (it must use the mock backends)
    /// [default: rigs/mock.toml of the current folder, else of Glint's source tree].
    #[arg(long, value_name = "FILE")]
    rig: Option<PathBuf>,
    /// Where the CSV and the chart go (fit_bench.csv, fit_bench.svg and the samples of one
    /// fit, samples_rect_800.csv, for benches/scipy_fit_timing.py; replaced if there).
    #[arg(long, value_name = "DIR", default_value = "bench-fit")]
    out: PathBuf,
    /// Timed repeats of each fit (the median is reported).
    #[arg(long, default_value_t = 15)]
    repeats: usize,
    /// Seeds of the random strategy at each count.
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    /// Simulated captures (each with its own sensor noise); errors are rms over them.
    #[arg(long, default_value_t = 4)]
    sessions: u64,
}

const COUNTS: [usize; 7] = [50, 100, 200, 400, 800, 1600, 2000];

struct Row {
    strategy: &'static str,
    session: u64,
    requested: usize,
    used: usize,
    seed: u64,
    ms_all: f64,
    n: f64,
    n_error: f64,
    ratio_error: f64,
    covered: bool,
    chosen: Model,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Median time (ms) of fitting every candidate model to the samples.
fn time_all(samples: &[Sample], repeats: usize) -> f64 {
    let opts = Options::default();
    median(
        (0..repeats.max(1))
            .map(|_| {
                let t = Instant::now();
                for m in Model::ALL {
                    std::hint::black_box(fit(m, std::hint::black_box(samples), &opts));
                }
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect(),
    )
}

pub fn fit_bench(a: FitBenchArgs) -> Result<ExitCode> {
    let rig_path = super::bench::mock_rig(a.rig.as_deref())?;
    let mut loaded = rig::load(&rig_path)?;
    let r = &loaded.rig;
    let truth = r
        .mock
        .clone()
        .context("the rig has no [mock] section; bench a mock rig")?
        .tile;
    if truth.model != glint::devices::mock::sim::Reflectance::BlinnPhong {
        bail!("the bench compares with a Blinn-Phong tile; set mock.tile.model = \"blinn-phong\"");
    }
    let n_true = truth.n;
    let ratio_true = truth.ks[1] / truth.kd[1];
    let mut rows = Vec::new();
    let strategies = [
        ("line", Strategy::Line),
        ("cross", Strategy::Cross),
        ("rect", Strategy::Rect),
        ("random", Strategy::Random),
    ];
    let base_seed = loaded.rig.mock.as_ref().map_or(0, |m| m.seed);
    for session in 0..a.sessions.max(1) {
        if let Some(m) = loaded.rig.mock.as_mut() {
            m.seed = base_seed + session;
        }
        let tmp = tempfile::tempdir()?;
        let s = tmp.path().join("s");
        eprintln!(
            "capture {} of {}: the simulated tile of {} ...",
            session + 1,
            a.sessions.max(1),
            rig_path.display()
        );
        let devs = devices::open(&loaded)?;
        capture::record(&loaded, devs, &s, Default::default(), &mut |_| {})?;
        // The response is recovered from each capture (no profile is read or stored).
        let hdr = glint::hdr::run::HdrOptions {
            recover: true,
            profile: Some(tmp.path().join("profile.json")),
            ..Default::default()
        };
        glint::hdr::run::run(&s, &hdr, &mut |_| {})?;
        glint::calib::run::run_session(&s, None)?;
        let inputs = load_inputs(&s)?;
        for (name, strategy) in strategies {
            for count in COUNTS {
                let seeds = if strategy == Strategy::Random {
                    a.seeds.max(1)
                } else {
                    1
                };
                for seed in 0..seeds {
                    let so = SampleOptions {
                        strategy,
                        count: Some(count),
                        seed: seed + 1,
                        saturation_level: inputs.saturation_level,
                        ..SampleOptions::default()
                    };
                    let sampled = sample(&inputs.scene, &inputs.image(), &so)?;
                    let samples: Vec<Sample> = sampled.samples.iter().map(|p| p.sample).collect();
                    if session == 0 && strategy == Strategy::Rect && count == 800 {
                        // The samples of one fit, for benches/scipy_fit_timing.py.
                        std::fs::create_dir_all(&a.out)?;
                        let p = a.out.join("samples_rect_800.csv");
                        std::fs::write(&p, glint::fit::run::samples_csv(&sampled, None))
                            .with_context(|| format!("writing {}", p.display()))?;
                    }
                    let ms_all = time_all(&samples, a.repeats);
                    let f = fit(Model::BlinnPhong, &samples, &Options::default());
                    let (train, test) = glint::fit::choose::halves(&samples);
                    let chosen = choose(&Model::ALL, &train, &test, &Options::default()).chosen;
                    let row = Row {
                        strategy: name,
                        session,
                        requested: count,
                        used: samples.len(),
                        seed: seed + 1,
                        ms_all,
                        n: f.n.value,
                        n_error: f.n.value / n_true - 1.0,
                        ratio_error: f.ratio[1].value / ratio_true - 1.0,
                        covered: f.n_ci95[0] <= n_true && n_true <= f.n_ci95[1],
                        chosen,
                    };
                    tracing::info!(
                    "{name:6} {count:5} -> {:4} samples: all models {:7.3} ms, n {:8.2} ({:+.2}%), ks/kd {:+.2}%, chosen {}",
                    row.used,
                    row.ms_all,
                    row.n,
                    100.0 * row.n_error,
                    100.0 * row.ratio_error,
                    row.chosen.name()
                );
                    rows.push(row);
                }
            }
        }
    }

    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let mut csv = String::from(
        "strategy,session,requested,used,seed,ms_all_models,n,n_error_pct,ks_over_kd_error_pct,n_ci95_covers,chosen\n",
    );
    for r in &rows {
        csv.push_str(&format!(
            "{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{},{}\n",
            r.strategy,
            r.session,
            r.requested,
            r.used,
            r.seed,
            r.ms_all,
            r.n,
            100.0 * r.n_error,
            100.0 * r.ratio_error,
            r.covered,
            r.chosen.name()
        ));
    }
    let csv_path = a.out.join("fit_bench.csv");
    std::fs::write(&csv_path, csv).with_context(|| format!("writing {}", csv_path.display()))?;
    let svg_path = a.out.join("fit_bench.svg");
    std::fs::write(&svg_path, chart(&rows).map_err(|e| anyhow::anyhow!(e))?)
        .with_context(|| format!("writing {}", svg_path.display()))?;

    println!(
        "Fit of every candidate model (Lambert, Phong, Blinn-Phong, cosine lobe), one core; truth Blinn-Phong n = {n_true}, ks/kd (green) = {ratio_true:.3}"
    );
    println!(
        "{:8} {:>6} {:>6} {:>12} {:>11} {:>13} {:>10}",
        "strategy", "asked", "used", "ms (all 4)", "n error", "ks/kd error", "chosen ok"
    );
    for (name, _) in strategies {
        for count in COUNTS {
            let v: Vec<&Row> = rows
                .iter()
                .filter(|r| r.strategy == name && r.requested == count)
                .collect();
            let k = v.len() as f64;
            let rms =
                |f: &dyn Fn(&Row) -> f64| (v.iter().map(|r| f(r).powi(2)).sum::<f64>() / k).sqrt();
            println!(
                "{:8} {:>6} {:>6} {:>12.3} {:>10.2}% {:>12.2}% {:>7}/{}",
                name,
                count,
                v.iter().map(|r| r.used).sum::<usize>() / v.len(),
                v.iter().map(|r| r.ms_all).sum::<f64>() / k,
                100.0 * rms(&|r| r.n_error),
                100.0 * rms(&|r| r.ratio_error),
                v.iter().filter(|r| r.chosen == Model::BlinnPhong).count(),
                v.len()
            );
        }
    }
    println!(
        "(errors: rms over {} captures{}; ms: mean)",
        a.sessions.max(1),
        format_args!(" and, for random, {} seeds per count", a.seeds.max(1))
    );
    println!("wrote {} and {}", csv_path.display(), svg_path.display());
    Ok(ExitCode::SUCCESS)
}

/// Fit time against |n error|, log-log, one line per strategy through its sample counts.
fn chart(rows: &[Row]) -> Result<String, String> {
    use plotters::prelude::*;
    glint::hdr::files::register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (800, 520)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let t_lo = rows.iter().map(|r| r.ms_all).fold(f64::INFINITY, f64::min) * 0.7;
        let t_hi = rows.iter().map(|r| r.ms_all).fold(0.0, f64::max) * 1.4;
        let e = |r: &Row| (100.0 * r.n_error.abs()).max(1e-3);
        let e_lo = rows.iter().map(e).fold(f64::INFINITY, f64::min) * 0.7;
        let e_hi = rows.iter().map(e).fold(0.0, f64::max) * 1.4;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                "Fit time (all four models, one core) against error in n",
                ("sans-serif", 20),
            )
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d((t_lo..t_hi).log_scale(), (e_lo..e_hi).log_scale())
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("fit time, ms")
            .y_desc("|n error|, %")
            .draw()
            .map_err(|e| e.to_string())?;
        let colours = [RED, GREEN, BLUE, MAGENTA];
        for (k, name) in ["line", "cross", "rect", "random"].iter().enumerate() {
            let col = colours[k];
            // Median time and rms error over captures and seeds at each count, joined in
            // order of count; the dots are single fits.
            let pts: Vec<(f64, f64)> = COUNTS
                .iter()
                .filter_map(|&c| {
                    let v: Vec<&Row> = rows
                        .iter()
                        .filter(|r| r.strategy == *name && r.requested == c)
                        .collect();
                    (!v.is_empty()).then(|| {
                        (
                            median(v.iter().map(|r| r.ms_all).collect()),
                            (v.iter().map(|r| e(r).powi(2)).sum::<f64>() / v.len() as f64).sqrt(),
                        )
                    })
                })
                .collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), col.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label(format!("{name} (50..2000 samples)"))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2))
                });
            chart
                .draw_series(
                    rows.iter()
                        .filter(|r| r.strategy == *name)
                        .map(|r| Circle::new((r.ms_all, e(r)), 3, col.filled())),
                )
                .map_err(|e| e.to_string())?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}
