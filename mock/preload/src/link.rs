//! The client side of the launcher's socket (protocol in the crate docs).
//!
//! Plain std I/O on a Unix stream: none of it goes through the hooked functions except
//! `close` when the stream is dropped, and the hook forwards that (the socket is not a
//! simulated device).

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;

pub struct Link {
    reader: BufReader<UnixStream>,
    writer: UnixStream,
}

/// A reply: `OK rest`, or the errno of `ERR <errno>`.
pub type Reply = Result<String, i32>;

/// A frame as the launcher sends it (its bytes already in the caller's buffer).
pub struct FrameMsg {
    pub sequence: u32,
    pub timestamp_ns: u64,
    pub error: bool,
    /// Bytes written to the buffer (the frame's, cut to the buffer's length).
    pub used: usize,
}

impl Link {
    pub fn connect(path: &str) -> std::io::Result<Link> {
        let s = UnixStream::connect(path)?;
        Ok(Link {
            reader: BufReader::new(s.try_clone()?),
            writer: s,
        })
    }

    fn read_line(&mut self) -> Result<String, i32> {
        let mut line = String::new();
        match self.reader.read_line(&mut line) {
            Ok(0) | Err(_) => Err(libc::ENODEV),
            Ok(_) => Ok(line.trim_end().to_string()),
        }
    }

    fn parse(line: String) -> Reply {
        if let Some(rest) = line.strip_prefix("OK") {
            Ok(rest.trim().to_string())
        } else if let Some(rest) = line.strip_prefix("ERR ") {
            Err(rest
                .split_whitespace()
                .next()
                .and_then(|e| e.parse().ok())
                .unwrap_or(libc::EIO))
        } else {
            Err(libc::EIO)
        }
    }

    /// Send one request line, read one reply line. A lost launcher is a gone device.
    pub fn call(&mut self, request: &str) -> Reply {
        if self
            .writer
            .write_all(format!("{request}\n").as_bytes())
            .is_err()
        {
            return Err(libc::ENODEV);
        }
        let line = self.read_line()?;
        Self::parse(line)
    }

    /// The device's state as a key/value map.
    pub fn state(&mut self) -> Result<HashMap<String, String>, i32> {
        let rest = self.call("STATE")?;
        Ok(rest
            .split_whitespace()
            .filter_map(|kv| kv.split_once('='))
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect())
    }

    /// Ask for the next frame (`nonblock`: EAGAIN rather than wait), read straight into
    /// `dst`; bytes beyond its length are read and dropped.
    pub fn dqbuf(&mut self, nonblock: bool, dst: &mut [u8]) -> Result<FrameMsg, i32> {
        if self
            .writer
            .write_all(if nonblock { b"DQBUF 1\n" } else { b"DQBUF 0\n" })
            .is_err()
        {
            return Err(libc::ENODEV);
        }
        let line = self.read_line()?;
        let Some(rest) = line.strip_prefix("FRAME ") else {
            return Self::parse(line).and(Err(libc::EIO));
        };
        let kv: HashMap<&str, u64> = rest
            .split_whitespace()
            .filter_map(|kv| kv.split_once('='))
            .filter_map(|(k, v)| Some((k, v.parse().ok()?)))
            .collect();
        let get = |k: &str| kv.get(k).copied().ok_or(libc::EIO);
        let len = get("bytes")?;
        let used = len.min(dst.len() as u64) as usize;
        self.reader
            .read_exact(&mut dst[..used])
            .map_err(|_| libc::ENODEV)?;
        let extra = len - used as u64;
        if extra > 0 {
            let copied = std::io::copy(&mut (&mut self.reader).take(extra), &mut std::io::sink())
                .map_err(|_| libc::ENODEV)?;
            if copied != extra {
                return Err(libc::ENODEV);
            }
        }
        Ok(FrameMsg {
            sequence: get("seq")? as u32,
            timestamp_ns: get("ts")?,
            error: get("error")? != 0,
            used,
        })
    }
}
