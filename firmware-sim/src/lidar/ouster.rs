//! Ouster (placeholder, filled in next).
