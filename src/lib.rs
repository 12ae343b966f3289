pub use glint_mock;
