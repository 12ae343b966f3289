//! `glint lamp off`: switch a rig's lamp off and read it back, touching nothing else.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use glint::devices::{self, LampOff};

#[derive(Subcommand)]
pub enum LampCommand {
    /// Switch the rig's lamp off and read it back; nothing else is opened or changed.
    ///
    /// For the times Glint could not do it itself: after `kill -9`, a crash or a power cut
    /// of a capture or daemon, after a third Ctrl-C (which quits at once), or from a
    /// service's `ExecStopPost` (docs/glint.service). Only the lamp's port is opened (not
    /// the camera), the rig's own protocol, timeout and tries are used, and the lamp's
    /// state is read back: exit status 0 means the lamp said it is off.
    ///
    /// A port another program holds (a running capture or daemon) is refused: it is that
    /// program's lamp (stop it with Ctrl-C, `glint abort` or `glint daemon stop`, which
    /// switch the lamp off). The simulated lab's lamp (lamp.backend = "mock") lives inside a
    /// running Glint and goes dark with it: there is nothing to switch (exit 0).
    #[command(after_help = "Examples:
  glint lamp off --rig /etc/glint/rig.toml        # after a crash: prints what it read back
  ExecStopPost=/usr/local/bin/glint lamp off --rig /etc/glint/rig.toml   # in a systemd unit

Exit status: 0 when the lamp read back off (or the rig's lamp is the simulated one); 1 with
a one-line error naming the cause (port missing or busy, no reply, still on) otherwise:
then the lamp may still be on.")]
    Off(OffArgs),
}

#[derive(Args)]
pub struct OffArgs {
    /// The rig file (TOML) whose [lamp] to switch off.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
}

pub fn cmd_lamp(c: LampCommand) -> Result<ExitCode> {
    match c {
        LampCommand::Off(a) => off(a),
    }
}

fn off(a: OffArgs) -> Result<ExitCode> {
    let loaded = glint::rig::load(&a.rig)?;
    let done = devices::lamp_off(&loaded).with_context(|| {
        format!(
            "switching off the lamp of {} (it may still be on)",
            a.rig.display()
        )
    })?;
    match done {
        LampOff::ReadBackOff { lamp } => println!("the {lamp} is off (read back)"),
        LampOff::Simulated => println!(
            "{}: the lamp is the simulated lab's (lamp.backend = \"mock\"), which goes dark with the Glint process that ran it: nothing to switch off",
            a.rig.display()
        ),
    }
    Ok(ExitCode::SUCCESS)
}
