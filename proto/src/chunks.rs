//! Reading a file as a stream of chunks, for the streamed uploads (`Upload`, `PutObject`) of
//! the client and the worker.

use std::sync::{Arc, Mutex};

use futures::Stream;
use tokio::io::AsyncReadExt;

/// Where a read error that ended a chunk stream early is left for the caller to report
/// (instead of the server's "stream ended" complaint).
pub type ReadErrorSlot = Arc<Mutex<Option<std::io::Error>>>;

/// `file` in pieces of `chunk_bytes` (the last one shorter). A read error ends the stream and
/// is stored in `error`.
pub fn file_chunks(
    file: tokio::fs::File,
    chunk_bytes: usize,
    error: ReadErrorSlot,
) -> impl Stream<Item = Vec<u8>> + Send + 'static {
    futures::stream::unfold(Some(file), move |file| {
        let error = error.clone();
        async move {
            let mut file = file?;
            let mut buf = vec![0u8; chunk_bytes];
            let mut filled = 0;
            while filled < chunk_bytes {
                match file.read(&mut buf[filled..]).await {
                    Ok(0) => break,
                    Ok(n) => filled += n,
                    Err(e) => {
                        *error.lock().expect("read-error slot") = Some(e);
                        return None;
                    }
                }
            }
            if filled == 0 {
                return None;
            }
            buf.truncate(filled);
            Some((buf, Some(file)))
        }
    })
}
