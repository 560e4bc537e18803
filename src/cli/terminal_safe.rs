//! Output that is safe to show on a terminal. Job names, errors and event messages come from
//! other people (any client may name a job), so control characters other than newline and
//! tab — escape sequences, carriage returns, bells, NUL, and the C1 controls U+0080–U+009F —
//! are shown as `?` instead of reaching the terminal.

use std::io::{self, Write};

/// Wraps a writer, replacing control characters as they pass.
pub struct TerminalSafe<W: Write> {
    inner: W,
    /// The previous write ended with 0xC2, the first byte of a C1 control's UTF-8 encoding.
    pending_c2: bool,
}

impl<W: Write> TerminalSafe<W> {
    pub fn new(inner: W) -> Self {
        Self {
            inner,
            pending_c2: false,
        }
    }
}

impl<W: Write> Write for TerminalSafe<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let mut out = Vec::with_capacity(buf.len() + 1);
        let mut bytes = buf.iter().copied().peekable();
        if std::mem::take(&mut self.pending_c2) {
            match bytes.peek() {
                Some(0x80..=0x9f) => {
                    bytes.next();
                    out.push(b'?');
                }
                _ => out.push(0xc2),
            }
        }
        while let Some(byte) = bytes.next() {
            match byte {
                b'\n' | b'\t' => out.push(byte),
                0x00..=0x1f | 0x7f => out.push(b'?'),
                0xc2 => match bytes.peek() {
                    Some(0x80..=0x9f) => {
                        bytes.next();
                        out.push(b'?');
                    }
                    None => self.pending_c2 = true,
                    Some(_) => out.push(byte),
                },
                _ => out.push(byte),
            }
        }
        self.inner.write_all(&out)?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        if std::mem::take(&mut self.pending_c2) {
            self.inner.write_all(&[0xc2])?;
        }
        self.inner.flush()
    }
}

impl<W: Write> Drop for TerminalSafe<W> {
    fn drop(&mut self) {
        let _ = self.flush();
    }
}

#[cfg(test)]
mod tests {
    use super::TerminalSafe;
    use std::io::Write;

    fn shown(pieces: &[&[u8]]) -> String {
        let mut out = Vec::new();
        {
            let mut safe = TerminalSafe::new(&mut out);
            for piece in pieces {
                safe.write_all(piece).unwrap();
            }
        }
        String::from_utf8(out).unwrap()
    }

    #[test]
    fn control_characters_do_not_reach_the_terminal() {
        let name = "job\x1b]0;pwned\x07\r\0 end\u{9b}2J é\n\tnext";
        assert_eq!(
            shown(&[name.as_bytes()]),
            "job?]0;pwned??? end?2J é\n\tnext"
        );
        // A C1 control (0xC2 0x9B) split across two writes, and a no-break space (0xC2 0xA0,
        // not a control) split the same way.
        let c1 = "a\u{9b}b".as_bytes();
        assert_eq!(shown(&[&c1[..2], &c1[2..]]), "a?b");
        let nbsp = "a\u{a0}b".as_bytes();
        assert_eq!(shown(&[&nbsp[..2], &nbsp[2..]]), "a\u{a0}b");
    }

    proptest::proptest! {
        #[test]
        fn no_control_character_gets_through(
            text in proptest::prelude::any::<String>(),
            split in proptest::prelude::any::<proptest::sample::Index>(),
        ) {
            let bytes = text.as_bytes();
            let at = split.index(bytes.len() + 1);
            let out = shown(&[&bytes[..at], &bytes[at..]]);
            proptest::prop_assert!(!out.chars().any(|c| c.is_control() && c != '\n' && c != '\t'));
            proptest::prop_assert_eq!(out.lines().count(), text.lines().count());
        }
    }
}
