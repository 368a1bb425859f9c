//! The byte buffer behind the streaming decoders of the vendor IMU protocols (Xsens, VectorNav):
//! messages that start with a sync byte and carry their own length and check. The decoder keeps
//! the bytes from a candidate sync byte on; when the candidate fails its check, only that one
//! byte is given up and the search goes on from the next sync byte in what is already buffered,
//! so a good message right behind noise (or behind a stray sync byte) is never lost.

/// A linear buffer of at most `N` bytes, oldest first.
#[derive(Debug)]
pub(crate) struct SyncBuf<const N: usize> {
    buf: [u8; N],
    len: usize,
}

impl<const N: usize> SyncBuf<N> {
    pub(crate) const fn new() -> Self {
        Self { buf: [0; N], len: 0 }
    }

    /// The buffered bytes.
    pub(crate) fn bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }

    /// Appends `b`; false (nothing appended) when full.
    pub(crate) fn push(&mut self, b: u8) -> bool {
        match self.buf.get_mut(self.len) {
            Some(slot) => {
                *slot = b;
                self.len += 1;
                true
            }
            None => false,
        }
    }

    /// Forgets the first `n` bytes (all of them when `n` is larger).
    pub(crate) fn drop_front(&mut self, n: usize) {
        let n = n.min(self.len);
        self.buf.copy_within(n..self.len, 0);
        self.len -= n;
    }

    /// Forgets the bytes before the first `sync` byte at or after index `from` (everything when
    /// there is none); returns how many were forgotten.
    pub(crate) fn skip_to_sync(&mut self, sync: u8, from: usize) -> usize {
        let from = from.min(self.len);
        let n = self.buf[from..self.len].iter().position(|&b| b == sync).map_or(self.len, |i| from + i);
        self.drop_front(n);
        n
    }
}

/// A streaming decoder over a [`SyncBuf`]: what [`feed`] needs of it.
pub(crate) trait Framed {
    /// What a decoded message gives.
    type Sample;
    /// Appends one byte; false when the buffer is full.
    fn push(&mut self, b: u8) -> bool;
    /// Decides the buffered candidates until one needs more bytes or yields a sample.
    fn poll(&mut self) -> Option<Self::Sample>;
    /// Forgets the candidate at the front (its sync byte) and the bytes up to the next one.
    fn give_up_candidate(&mut self);
}

/// Consumes bytes from `input` until a sample is complete. Returns the number of bytes consumed
/// (possibly 0 when a sample was already buffered) and the sample, if any; call it again with
/// the rest of the input until everything is consumed and no sample comes.
pub(crate) fn feed<F: Framed>(dec: &mut F, input: &[u8]) -> (usize, Option<F::Sample>) {
    if let Some(s) = dec.poll() {
        return (0, Some(s));
    }
    for (i, &b) in input.iter().enumerate() {
        if !dec.push(b) {
            // Unreachable (a candidate is decided once its length is buffered, and no length
            // exceeds the buffer), but a full buffer must not stall the stream.
            dec.give_up_candidate();
            dec.push(b);
        }
        if let Some(s) = dec.poll() {
            return (i + 1, Some(s));
        }
    }
    (input.len(), None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn push_drop_and_resync() {
        let mut b = SyncBuf::<4>::new();
        for x in [1, 0xFA, 3, 0xFA] {
            assert!(b.push(x));
        }
        assert!(!b.push(9));
        assert_eq!(b.skip_to_sync(0xFA, 0), 1);
        assert_eq!(b.bytes(), &[0xFA, 3, 0xFA]);
        assert_eq!(b.skip_to_sync(0xFA, 1), 2);
        assert_eq!(b.bytes(), &[0xFA]);
        assert_eq!(b.skip_to_sync(0xFA, 1), 1);
        assert!(b.bytes().is_empty());
        b.drop_front(5);
        assert!(b.bytes().is_empty());
    }
}
