//! Who performs the hands-on steps: a person at the terminal, or the rig's configured
//! commands (`[operator]`), for a rig that places the tile itself: a robot arm, a slide, or
//! the simulated lab's `glint-mock scene`.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::error::DeviceError;
use crate::rig::{OperatorSection, Rig};
use crate::traits::{Operator, OperatorAction};

/// The operator a rig names: its `[operator]` commands, or a person at the console.
pub fn for_rig(rig: &Rig) -> Box<dyn Operator> {
    match &rig.operator {
        Some(o) => Box::new(CommandOperator::new(o.clone())),
        None => Box::new(ConsoleOperator),
    }
}

/// A person at the terminal: asked on stderr, answers with Enter.
pub struct ConsoleOperator;

impl Operator for ConsoleOperator {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        use std::io::{BufRead, IsTerminal, Write};
        if !std::io::stdin().is_terminal() {
            return Err(DeviceError::Operator(format!(
                "the capture needs someone to {action}, but standard input is not a terminal; run `glint capture` from a terminal"
            )));
        }
        eprint!("Please {action}, then press Enter (Ctrl-C aborts): ");
        let _ = std::io::stderr().flush();
        let mut line = String::new();
        std::io::stdin()
            .lock()
            .read_line(&mut line)
            .map_err(|e| DeviceError::Operator(format!("could not read the answer: {e}")))?;
        Ok(())
    }
}

/// Runs the rig's configured command for each action, without a shell; the action is done
/// when the command exits 0.
pub struct CommandOperator {
    cfg: OperatorSection,
}

/// The most of a failing command's standard error kept for the message.
const STDERR_KEEP: usize = 4096;

impl CommandOperator {
    pub fn new(cfg: OperatorSection) -> Self {
        CommandOperator { cfg }
    }

    /// The configured command for an action and its arguments: for a board pose the
    /// pose's flags are appended (`--pose K --tilt-x-deg A --tilt-y-deg B --rotate-deg C
    /// --lift-mm H`, what `glint-mock scene show-board` takes).
    fn command(&self, action: OperatorAction) -> (&'static str, Vec<String>) {
        match action {
            OperatorAction::PlaceTile => ("operator.place_tile", self.cfg.place_tile.clone()),
            OperatorAction::RemoveTile => ("operator.remove_tile", self.cfg.remove_tile.clone()),
            OperatorAction::ShowBoard(p) => {
                let mut argv = self.cfg.show_board.clone();
                if !argv.is_empty() {
                    argv.extend([
                        "--pose".to_string(),
                        p.index.to_string(),
                        "--tilt-x-deg".into(),
                        p.tilt_x_deg.to_string(),
                        "--tilt-y-deg".into(),
                        p.tilt_y_deg.to_string(),
                        "--rotate-deg".into(),
                        p.rotate_deg.to_string(),
                        "--lift-mm".into(),
                        p.lift_mm.to_string(),
                    ]);
                }
                ("operator.show_board", argv)
            }
        }
    }
}

impl Operator for CommandOperator {
    fn perform(&mut self, action: OperatorAction) -> Result<(), DeviceError> {
        let (key, argv) = self.command(action);
        let Some((program, args)) = argv.split_first() else {
            return Err(DeviceError::Operator(format!(
                "{key} is empty; name the program that will {action}"
            )));
        };
        let shown = argv.join(" ");
        tracing::info!("operator: running {key}: {shown}");
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                DeviceError::Operator(format!(
                    "cannot run {key} (`{program}`): {e}; check that the program exists and is on PATH"
                ))
            })?;
        // Read standard error on the side, so a chatty command cannot block on a full pipe.
        let mut stderr = child.stderr.take();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut all = Vec::new();
            if let Some(s) = stderr.as_mut() {
                let mut buf = [0u8; 4096];
                while let Ok(n) = s.read(&mut buf) {
                    if n == 0 {
                        break;
                    }
                    all.extend_from_slice(&buf[..n]);
                    if all.len() > 2 * STDERR_KEEP {
                        all.drain(..all.len() - STDERR_KEEP);
                    }
                }
            }
            let _ = tx.send(all);
        });
        let timeout = Duration::from_millis(self.cfg.timeout_ms);
        let start = Instant::now();
        let status = loop {
            match child.try_wait() {
                Ok(Some(status)) => break status,
                Ok(None) if start.elapsed() >= timeout => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(DeviceError::Operator(format!(
                        "{key} (`{shown}`) did not finish within {} ms (operator.timeout_ms); it was stopped",
                        self.cfg.timeout_ms
                    )));
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(10)),
                Err(e) => {
                    return Err(DeviceError::Operator(format!(
                        "{key} (`{shown}`): cannot wait for it: {e}"
                    )))
                }
            }
        };
        // A process the command left behind may hold its standard error open: do not wait
        // for that.
        let err = rx.recv_timeout(Duration::from_secs(1)).unwrap_or_default();
        if status.success() {
            return Ok(());
        }
        let last = String::from_utf8_lossy(&err)
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .map(|l| format!(": {}", l.trim().chars().take(300).collect::<String>()))
            .unwrap_or_default();
        Err(DeviceError::Operator(format!(
            "{key} (`{shown}`) failed ({status}){last}; the scene was not changed to {action}"
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(place: &[&str], timeout_ms: u64) -> CommandOperator {
        CommandOperator::new(OperatorSection {
            place_tile: place.iter().map(|s| s.to_string()).collect(),
            remove_tile: vec!["true".into()],
            show_board: vec!["true".into()],
            timeout_ms,
        })
    }

    #[test]
    fn a_command_that_exits_0_performs_the_action() {
        op(&["true"], 5000)
            .perform(OperatorAction::PlaceTile)
            .unwrap();
        op(&["sh", "-c", "exit 0"], 5000)
            .perform(OperatorAction::RemoveTile)
            .unwrap();
    }

    #[test]
    fn a_failing_command_names_itself_and_its_last_error_line() {
        let e = op(&["sh", "-c", "echo 'arm: gripper open' >&2; exit 3"], 5000)
            .perform(OperatorAction::PlaceTile)
            .unwrap_err()
            .to_string();
        assert!(e.contains("operator.place_tile"), "{e}");
        assert!(e.contains("arm: gripper open"), "{e}");
        assert!(e.contains("3"), "{e}");
        assert!(!e.contains('\n'), "{e}");
    }

    #[test]
    fn a_missing_program_and_a_hung_command_are_clear_errors() {
        let e = op(&["/nonexistent/glint-robot"], 5000)
            .perform(OperatorAction::PlaceTile)
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot run operator.place_tile"), "{e}");
        let t = Instant::now();
        let e = op(&["sleep", "30"], 200)
            .perform(OperatorAction::PlaceTile)
            .unwrap_err()
            .to_string();
        assert!(e.contains("did not finish within 200 ms"), "{e}");
        assert!(t.elapsed() < Duration::from_secs(10));
    }
}
