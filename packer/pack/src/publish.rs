//! Publishing a file: written under a temporary name beside its final one (with a
//! published file's mode), made durable (written back while it grows, synced, the folder
//! synced) and renamed into place, so that a crash never leaves a partial file under the
//! final name. Where the filesystem can insert a range at the start of a file, the data
//! already written stays where it is and the front is written before it.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// A piece of a file being published: bytes, the first `len` bytes of a temporary file,
/// or a gap of unwritten bytes (a hole; zeros when read).
pub(crate) enum Part<'a> {
    Bytes(&'a [u8]),
    File(&'a mut File, u64),
    Gap(u64),
}

/// Writes `parts` to a temporary file in `folder`, makes it `len` bytes long, syncs it
/// (if `durable`) and renames it to `path`: nothing is left under the final name on error.
pub(crate) fn publish<'a>(
    path: &Path,
    folder: &Path,
    parts: impl IntoIterator<Item = Part<'a>>,
    len: u64,
    durable: bool,
) -> Result<()> {
    let mut out = partial_file(path, folder)?;
    write_parts(path, folder, out.as_file_mut(), parts)?;
    let (file, temp) = out.into_parts();
    put_in_place(path, folder, (&file, temp), len, durable)
}

/// A new temporary file beside `path` (in `folder`), named after it, that becomes the
/// archive when renamed.
pub(crate) fn partial_file(path: &Path, folder: &Path) -> Result<tempfile::NamedTempFile> {
    let file_name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    published(tempfile::Builder::new().prefix(&format!(".{file_name}.")).suffix(".partial"))
        .tempfile_in(folder)
        .map_err(|e| Error::file(folder, e))
}

/// Writes `parts` to `file` from where it stands.
pub(crate) fn write_parts<'a>(
    path: &Path,
    folder: &Path,
    file: &mut File,
    parts: impl IntoIterator<Item = Part<'a>>,
) -> Result<()> {
    let io = |e: std::io::Error| Error::file(path, e);
    for part in parts {
        match part {
            Part::Bytes(bytes) => file.write_all(bytes).map_err(io)?,
            Part::Gap(0) => {}
            Part::Gap(n) => {
                let gap = i64::try_from(n).map_err(|_| io(std::io::Error::other("a gap over 2^63 bytes")))?;
                file.seek(SeekFrom::Current(gap)).map_err(io)?;
            }
            Part::File(source, len) => {
                source.seek(SeekFrom::Start(0)).map_err(|e| temporary(folder, e))?;
                let copied = std::io::copy(&mut Read::take(source, len), file).map_err(io)?;
                if copied != len {
                    let short = std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "shorter than written");
                    return Err(temporary(folder, short));
                }
            }
        }
    }
    Ok(())
}

/// Makes the temporary `file` `len` bytes long, syncs it (if `durable`) and renames it to
/// `path`; then syncs the folder, so that the rename lasts too.
pub(crate) fn put_in_place(
    path: &Path,
    folder: &Path,
    (file, temp): (&File, tempfile::TempPath),
    len: u64,
    durable: bool,
) -> Result<()> {
    let io = |e: std::io::Error| Error::file(path, e);
    file.set_len(len).map_err(io)?;
    if durable {
        file.sync_all().map_err(io)?;
    }
    temp.persist(path).map_err(|e| Error::file(path, e.error))?;
    if durable {
        sync_folder(folder);
    }
    Ok(())
}

/// Inserts `len` bytes (a hole) at the start of `file`, shifting its contents, without
/// copying them; false where the filesystem cannot (or `len` is not a multiple of its
/// block size), and the file is then unchanged.
#[cfg(target_os = "linux")]
pub(crate) fn insert_range(file: &File, len: u64) -> bool {
    use rustix::fs::{FallocateFlags, fallocate};
    len > 0 && fallocate(file, FallocateFlags::INSERT_RANGE, 0, len).is_ok()
}

/// Data written between syncs of a durable archive's data while it is written.
pub(crate) const WRITE_BACK_BYTES: u64 = 2 << 20;

/// Syncs a durable archive's data file on a thread of its own each time it is woken
/// (woken again while syncing: once more after), so that the disk writes the data while
/// tiles are still being added. A sync costs about the bytes it must write; on a virtual
/// disk, whose host caches writes until asked to flush, no hint starts that early (the
/// write-back hint this replaced left the final sync as long: 41 ms after 200 ms of
/// quiet for 36 MB, against 3-8 ms left with syncs on the way). Its error goes to
/// [`Writer::finish`] (the final sync on the same open file would not see it again).
pub(crate) struct Syncer {
    wake: Option<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<std::io::Result<()>>>,
}

impl Syncer {
    /// A syncer of `file`, syncing it once now.
    pub(crate) fn start(file: &File) -> std::io::Result<Self> {
        let file = file.try_clone()?;
        let (wake, woken) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::Builder::new().name("archive sync".into()).spawn(move || {
            file.sync_data()?;
            while woken.recv().is_ok() {
                while woken.try_recv().is_ok() {}
                file.sync_data()?;
            }
            Ok(())
        })?;
        Ok(Self { wake: Some(wake), thread: Some(thread) })
    }

    pub(crate) fn wake(&self) {
        if let Some(wake) = &self.wake {
            // The thread is gone only after a failed sync, which `stop` reports.
            let _ = wake.send(());
        }
    }

    /// Ends the thread once its sync in progress (and one asked for) is done; the first
    /// error of any of its syncs.
    pub(crate) fn stop(&mut self) -> std::io::Result<()> {
        self.wake = None;
        match self.thread.take() {
            Some(thread) => thread.join().unwrap_or_else(|_| Err(std::io::Error::other("the sync thread panicked"))),
            None => Ok(()),
        }
    }
}

impl Drop for Syncer {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

#[cfg(not(target_os = "linux"))]
pub(crate) fn insert_range(_file: &File, _len: u64) -> bool {
    false
}

/// An I/O error on one of the writer's temporary files in `folder`.
pub(crate) fn temporary(folder: &Path, error: std::io::Error) -> Error {
    Error::Temporary { folder: folder.to_path_buf(), error }
}

/// The folder a file will be published in: temporary files go there, so that the final
/// rename stays on one filesystem and is atomic.
pub fn output_folder(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Makes the rename durable. Best effort: not every platform can open a folder.
pub(crate) fn sync_folder(folder: &Path) {
    if let Ok(dir) = File::open(folder) {
        let _ = dir.sync_all();
    }
}

/// A temporary file that is renamed into place when done gets a published file's mode
/// (0666 less the umask, as any new file), not the private 0600 of temporary files: a
/// web server running as another user must be able to read the archive.
pub(crate) fn published<'s, 'a, 'b>(builder: &'s mut tempfile::Builder<'a, 'b>) -> &'s mut tempfile::Builder<'a, 'b> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666))
    }
    #[cfg(not(unix))]
    {
        builder
    }
}
