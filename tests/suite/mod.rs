mod cli;
mod emor;
mod faults;
mod lamp;
mod latency;
mod rig_files;
mod sessions;
mod util;
