//! `glint export`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use glint::export;
use glint::fit::model::Reflectance;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Target {
    /// Mitsuba 3: a `<bsdf>` (diffuse, or roughplastic fitted to the model).
    Mitsuba,
    /// glTF 2.0: a .gltf with the material (metallic-roughness + KHR_materials_specular)
    /// on a small quad.
    Gltf,
    /// A plain JSON record of the fitted parameters with their uncertainties.
    Json,
}

impl Target {
    fn ext(self) -> &'static str {
        match self {
            Target::Mitsuba => "xml",
            Target::Gltf => "gltf",
            Target::Json => "json",
        }
    }
    fn name(self) -> &'static str {
        match self {
            Target::Mitsuba => "mitsuba",
            Target::Gltf => "gltf",
            Target::Json => "json",
        }
    }
}

#[derive(Args)]
pub struct ExportArgs {
    /// A fitted session (glint fit): reads SESSION/fit/fit.json and fit/samples.csv.
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// The format to write.
    #[arg(long, value_enum)]
    to: Target,
    /// The model to export (lambert, phong, blinn-phong, cosine-lobe, ggx); default: the one
    /// the fit chose.
    #[arg(long, value_name = "M")]
    model: Option<String>,
    /// Where to write; default SESSION/export/<model>.<xml|gltf|json>.
    #[arg(long, value_name = "PATH")]
    out: Option<PathBuf>,
    /// For a session in relative units (no reference target): your assumed diffuse albedo
    /// of the brightest channel, in (0, 1]; the whole BRDF is scaled by one factor so that
    /// ks/kd and n stay as fitted. Recorded in the file. Needed by mitsuba and gltf.
    #[arg(long, value_name = "A")]
    albedo: Option<f64>,
    /// Replace an existing file at the output path (atomically); without it an existing
    /// file is never replaced.
    #[arg(long)]
    force: bool,
    /// Export from a session that is not complete (with a warning).
    #[arg(long)]
    allow_incomplete: bool,
}

pub fn cmd_export(a: ExportArgs) -> Result<ExitCode> {
    let loaded = export::load_allowing(&a.session, a.model.as_deref(), a.allow_incomplete)?;
    for w in &loaded.warnings {
        eprintln!("warning: {w}");
    }
    let out = match &a.out {
        Some(o) => o.clone(),
        None => a
            .session
            .join("export")
            .join(format!("{}.{}", loaded.model.name(), a.to.ext())),
    };
    // Checked before the (seconds long) conversion, and again by the write itself.
    if !a.force && out.symlink_metadata().is_ok() {
        bail!(
            "{} exists; give another --out, or --force to replace it",
            out.display()
        );
    }
    let text = match a.to {
        Target::Json => {
            if a.albedo.is_some() {
                bail!("--albedo is for --to mitsuba and --to gltf; the json record keeps the session's own units: drop it");
            }
            let v = export::json_record(&loaded);
            eprintln!(
                "{}: model {}, units {}",
                a.to.name(),
                loaded.model.name(),
                v["units"].as_str().unwrap_or("?")
            );
            serde_json::to_string_pretty(&v)? + "\n"
        }
        Target::Mitsuba => {
            let m = export::material(&loaded, a.albedo, "Mitsuba")?;
            let f = export::fit_mitsuba(&loaded, &m);
            eprintln!(
                "mitsuba {}{}: {}",
                f.plugin,
                if f.plugin == "roughplastic" {
                    format!(" ({}, alpha {:.5})", f.distribution.name(), f.alpha)
                } else {
                    String::new()
                },
                export::describe_errors(&f.errors)
            );
            for w in &f.warnings {
                eprintln!("warning: {w}");
            }
            export::mitsuba_xml(&loaded, &m, &f)
        }
        Target::Gltf => {
            let m = export::material(&loaded, a.albedo, "glTF")?;
            let f = export::fit_gltf(&loaded, &m);
            eprintln!(
                "gltf: roughness {:.5} (GGX alpha {:.5}), specularFactor {:.3}, specularColorFactor [{}]: {}",
                f.roughness,
                f.alpha,
                f.specular_factor,
                f.specular_color
                    .iter()
                    .map(|x| format!("{x:.3}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                export::describe_errors(&f.errors)
            );
            for w in &f.warnings {
                eprintln!("warning: {w}");
            }
            serde_json::to_string_pretty(&export::gltf_json(&loaded, &m, &f))? + "\n"
        }
    };
    write(&out, text.as_bytes(), a.force, a.out.is_none())?;
    println!("{}", out.display());
    Ok(ExitCode::SUCCESS)
}

/// Write `bytes` to `out`: created new (never replacing, never following a link), or with
/// `force` replaced atomically (a link there is replaced, not followed). The default
/// folder SESSION/export is made when `make_dir`.
fn write(out: &Path, bytes: &[u8], force: bool, make_dir: bool) -> Result<()> {
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if make_dir {
        glint::fsx::ensure_dir(&parent)
            .map_err(|e| anyhow::anyhow!("cannot make {} ({e})", parent.display()))?;
    } else if !parent.is_dir() {
        bail!(
            "{}: no such folder for --out; make it first or give another --out",
            parent.display()
        );
    }
    if force {
        glint::session::write_replace(out, bytes)?;
        return Ok(());
    }
    glint::fsx::create_new(out, bytes).map_err(|e| {
        if e.kind() == std::io::ErrorKind::AlreadyExists {
            anyhow::anyhow!(
                "{} exists; give another --out, or --force to replace it",
                out.display()
            )
        } else {
            anyhow::anyhow!("cannot write {} ({e})", out.display())
        }
    })
}
