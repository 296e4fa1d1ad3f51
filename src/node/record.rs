//! The recorder (`minflow record`, like `ros2 bag record`): subscribes to topics and writes
//! every valid frame that arrives into MCAP bags in an output folder, rosbag2-style:
//! `OUT/OUT_0.mcap`, `OUT/OUT_1.mcap`, ... (split by `--max-bag-size` / `--max-bag-duration`)
//! and `OUT/metadata.yaml` (rosbag2's bag information, so `ros2 bag info OUT` and `ros2 bag
//! play OUT` work on the folder).
//!
//! Nothing received is lost to a clean stop: on SIGINT/SIGTERM the subscriptions are
//! dropped, every frame already received is written and the bag is finished. Against
//! SIGKILL, the current chunk is closed and flushed every `flush_interval`, so a killed
//! recorder leaves a bag readable up to its last flushed chunk. A payload that is not a
//! valid frame is counted as malformed and logged (first one per topic, then every 100th),
//! never written. Messages keep the frame's stamp as log and publish time (docs/design.md,
//! "Bags"), and their bytes as they travelled where the transport carries CDR.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, RecvTimeoutError};
use std::time::{Duration, Instant};

use crate::bag::{BagError, BagWriter};
use crate::msgs::ParticleFrame;
use crate::transport::{Counters, Sample, Transport, TransportError};
use crate::viz::cloud::WritePoints;

mod folder;
mod metadata;
use folder::prepare_folder;
pub use folder::LOCK_FILE;
use metadata::write_metadata;

/// What to record and when to split or stop.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// ROS 2 topic names to subscribe to.
    pub topics: Vec<String>,
    /// Output folder (created; must not hold bags already).
    pub out: PathBuf,
    /// Start a new file once the current one reaches this many bytes.
    pub max_bag_size: Option<u64>,
    /// Start a new file after this much wall time.
    pub max_bag_duration: Option<Duration>,
    /// Stop after this much wall time.
    pub duration: Option<Duration>,
    /// Stop after this many frames written.
    pub count: Option<u64>,
    /// Close and flush the current chunk this often (bounds what SIGKILL can lose).
    pub flush_interval: Duration,
    /// Delete bags and metadata.yaml already in the output folder instead of refusing.
    pub overwrite: bool,
    /// Stop once this long passed without a message, after the first one.
    pub idle_exit: Option<Duration>,
    /// Also write every frame as a `foxglove.PointCloud` on `<topic>/points`
    /// ([`crate::viz::points_topic`]), for Foxglove's 3D panel. Not counted in `written`,
    /// not listed in metadata.yaml (ROS 2 does not play protobuf).
    pub points: bool,
}

/// What a recording wrote.
#[derive(Debug, Clone, Default)]
pub struct RecordReport {
    /// Frames written, all files.
    pub written: u64,
    /// Payloads that were not valid frames (not written).
    pub malformed: u64,
    /// Bag files written, in order.
    pub files: Vec<PathBuf>,
    /// Frames written per topic.
    pub per_topic: BTreeMap<String, u64>,
}

/// Errors that stop a recording.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// Writing a bag failed.
    #[error(transparent)]
    Bag(#[from] BagError),
    /// Subscribing failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The output folder is unusable.
    #[error("output folder {path}: {reason}")]
    Out { path: PathBuf, reason: String },
    /// Another recorder holds the output folder's lock ([`LOCK_FILE`]).
    #[error(
        "output folder {path}: another recorder is writing here (process {holder}); stop it or \
         choose another folder"
    )]
    Locked {
        path: PathBuf,
        /// The holder's process id as its lock file says, or `unknown`.
        holder: String,
    },
    /// A file of the output folder (its lock file, metadata.yaml) could not be written.
    #[error("{path}: {source}")]
    File {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Writing the open bag failed (a full disk): it was closed at its last flush, so the
    /// frames flushed before stay a complete bag; those after were lost.
    #[error(
        "recording into {path} stopped: {kept} frames kept in it, the {lost} written since its \
         last flush lost"
    )]
    Lost {
        /// The bag that was being written.
        path: PathBuf,
        /// Frames in the bag as it was closed.
        kept: u64,
        /// Frames written into it after its last flush.
        lost: u64,
        /// What failed.
        #[source]
        source: Box<RecordError>,
    },
    /// metadata.yaml could not be serialised.
    #[error("{path}: {source}")]
    Metadata {
        path: PathBuf,
        #[source]
        source: serde_yaml_ng::Error,
    },
}

/// One bag file being written.
struct OpenBag {
    writer: BagWriter,
    opened: Instant,
    /// Uncompressed bytes written since the last flush (the file size lags until then).
    pending: u64,
    info: FileInfo,
    /// `info` as of the last flush: what a failed write leaves in the file.
    flushed: FileInfo,
}

/// Per-file numbers for metadata.yaml.
#[derive(Debug, Clone, Default)]
struct FileInfo {
    path: PathBuf,
    first_ns: Option<u64>,
    last_ns: u64,
    count: u64,
    per_topic: BTreeMap<String, u64>,
}

impl FileInfo {
    fn add(&mut self, topic: &str, stamp_ns: u64) {
        self.first_ns = Some(self.first_ns.map_or(stamp_ns, |f| f.min(stamp_ns)));
        self.last_ns = self.last_ns.max(stamp_ns);
        self.count += 1;
        *self.per_topic.entry(topic.to_owned()).or_default() += 1;
    }
}

/// The rosbag2 base name of an output folder: its last component.
fn base_name(out: &Path) -> String {
    out.file_name().map_or_else(
        || "rosbag2".to_owned(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// Records until `stop`, `--duration` or `--count`. `progress` is called with the frames
/// written so far after each one.
///
/// # Errors
/// [`RecordError`]: another recorder holds the folder ([`LOCK_FILE`]), the folder holds bags
/// already, a subscription or a write failed.
pub fn record(
    options: &RecordOptions,
    transport: &dyn Transport,
    counters: &Counters,
    stop: &AtomicBool,
    progress: impl FnMut(u64),
) -> Result<RecordReport, RecordError> {
    let out = &options.out;
    let _lock = prepare_folder(options)?;
    let (tx, rx) = channel();
    let mut subscriptions = Vec::new();
    for topic in &options.topics {
        subscriptions.push(transport.subscribe(topic, tx.clone())?);
    }
    drop(tx);
    tracing::info!(
        "recording {} over {} into {}",
        options.topics.join(" "),
        transport.kind(),
        out.display()
    );

    let mut files = Files::new(options);
    let pumped = pump(
        options,
        &rx,
        &mut subscriptions,
        &mut files,
        counters,
        stop,
        progress,
    );
    drop(subscriptions);
    match pumped.and_then(|()| files.finish()) {
        Ok(report) => Ok(report),
        Err(e) => Err(files.salvage(e)),
    }
}

/// Receives and writes until a stop condition, then drains what already arrived.
fn pump(
    options: &RecordOptions,
    rx: &std::sync::mpsc::Receiver<Sample>,
    subscriptions: &mut Vec<Box<dyn crate::transport::Subscription>>,
    files: &mut Files,
    counters: &Counters,
    stop: &AtomicBool,
    mut progress: impl FnMut(u64),
) -> Result<(), RecordError> {
    let started = Instant::now();
    let mut done = false;
    let mut last_message: Option<Instant> = None;
    loop {
        let idle = options
            .idle_exit
            .is_some_and(|d| last_message.is_some_and(|t| t.elapsed() >= d));
        let stop_now = idle
            || stop.load(Ordering::Relaxed)
            || options.duration.is_some_and(|d| started.elapsed() >= d)
            || options.count.is_some_and(|n| files.report.written >= n);
        if stop_now && !done {
            // Stop receiving, then write what already arrived.
            done = true;
            subscriptions.clear();
        }
        let sample = if done {
            match rx.try_recv() {
                Ok(s) => s,
                Err(_) => break,
            }
        } else {
            match rx.recv_timeout(Duration::from_millis(50)) {
                Ok(s) => s,
                Err(RecvTimeoutError::Timeout) => {
                    files.flush_if_due()?;
                    continue;
                }
                Err(RecvTimeoutError::Disconnected) => break,
            }
        };
        counters.received();
        last_message = Some(Instant::now());
        if options.count.is_some_and(|n| files.report.written >= n) {
            continue;
        }
        let Some((bytes, stamp_ns, frame)) = files.validate(&sample, counters) else {
            continue;
        };
        files.write(&sample.topic, stamp_ns, &bytes)?;
        if options.points {
            files.write_points(&sample.topic, stamp_ns, &frame)?;
        }
        progress(files.report.written);
        files.flush_if_due()?;
    }
    Ok(())
}

/// The bag files of a recording: the one being written, those finished, and the counts.
struct Files<'a> {
    options: &'a RecordOptions,
    /// rosbag2 base name of the files (the folder's name).
    base: String,
    report: RecordReport,
    /// Finished files, in order.
    infos: Vec<FileInfo>,
    bag: Option<OpenBag>,
    last_flush: Instant,
    malformed_per_topic: BTreeMap<String, u64>,
}

impl<'a> Files<'a> {
    /// No file open yet.
    fn new(options: &'a RecordOptions) -> Self {
        Files {
            options,
            base: base_name(&options.out),
            report: RecordReport::default(),
            infos: Vec::new(),
            bag: None,
            last_flush: Instant::now(),
            malformed_per_topic: BTreeMap::new(),
        }
    }

    /// The sample's CDR bytes and its frame's stamp (ns), or None when it is not a valid
    /// frame (counted as malformed; logged for the first one per topic, then every 100th).
    fn validate(
        &mut self,
        sample: &Sample,
        counters: &Counters,
    ) -> Option<(Vec<u8>, u64, ParticleFrame)> {
        let validated = sample.cdr().map_err(|e| e.to_string()).and_then(|bytes| {
            let frame = crate::msgs::decode(&bytes).map_err(|e| e.to_string())?;
            let stamp = frame
                .header
                .stamp
                .as_unsigned_nanos()
                .ok_or("negative stamp")?;
            Ok((bytes, stamp, frame))
        });
        match validated {
            Ok(v) => Some(v),
            Err(reason) => {
                counters.malformed();
                self.report.malformed += 1;
                let n = self
                    .malformed_per_topic
                    .entry(sample.topic.clone())
                    .or_default();
                *n += 1;
                if *n == 1 || *n % 100 == 0 {
                    tracing::warn!(
                        "{}: malformed frame #{n} not recorded: {reason}",
                        sample.topic
                    );
                }
                None
            }
        }
    }

    /// Writes one message, first closing the current file when it reached
    /// `--max-bag-size` or `--max-bag-duration` and opening the next one if none is open.
    fn write(&mut self, topic: &str, stamp_ns: u64, bytes: &[u8]) -> Result<(), RecordError> {
        let options = self.options;
        let split = self.bag.as_ref().is_some_and(|b| {
            options
                .max_bag_size
                .is_some_and(|max| b.writer.bytes_written() + b.pending >= max)
                || options
                    .max_bag_duration
                    .is_some_and(|d| b.opened.elapsed() >= d)
        });
        if split {
            self.close_open()?;
        }
        let open = match &mut self.bag {
            Some(b) => b,
            None => {
                let path = options
                    .out
                    .join(format!("{}_{}.mcap", self.base, self.infos.len()));
                tracing::info!("writing {}", path.display());
                let info = FileInfo {
                    path: path.clone(),
                    ..FileInfo::default()
                };
                self.bag.insert(OpenBag {
                    writer: BagWriter::create(&path)?,
                    opened: Instant::now(),
                    pending: 0,
                    flushed: info.clone(),
                    info,
                })
            }
        };
        open.writer.write_raw(topic, stamp_ns, bytes)?;
        open.pending += bytes.len() as u64;
        open.info.add(topic, stamp_ns);
        self.report.written += 1;
        *self.report.per_topic.entry(topic.to_owned()).or_default() += 1;
        Ok(())
    }

    /// Writes `frame`'s point cloud into the open file (opened by [`Files::write`] just before).
    fn write_points(
        &mut self,
        topic: &str,
        stamp_ns: u64,
        frame: &ParticleFrame,
    ) -> Result<(), RecordError> {
        if let Some(open) = self.bag.as_mut() {
            let points = crate::viz::points_topic(topic);
            open.writer.write_points(&points, stamp_ns, frame)?;
            open.pending += (frame.len() * crate::viz::cloud::POINT_STRIDE as usize) as u64;
        }
        Ok(())
    }

    /// Closes and flushes the current chunk when `flush_interval` passed since the last time.
    fn flush_if_due(&mut self) -> Result<(), RecordError> {
        flush_if_due(
            &mut self.bag,
            &mut self.last_flush,
            self.options.flush_interval,
        )
    }

    /// Flushes the open file (a failure leaves it open for [`Files::salvage`]), then
    /// finishes it.
    fn close_open(&mut self) -> Result<(), RecordError> {
        if let Some(b) = self.bag.as_mut() {
            b.writer.flush()?;
            b.pending = 0;
            b.flushed = b.info.clone();
        }
        if let Some(b) = self.bag.take() {
            self.infos.push(close(b, &mut self.report)?);
        }
        Ok(())
    }

    /// Finishes the open file and writes metadata.yaml; returns the totals.
    fn finish(&mut self) -> Result<RecordReport, RecordError> {
        self.close_open()?;
        write_metadata(&self.options.out, &self.infos)?;
        Ok(std::mem::take(&mut self.report))
    }

    /// After `error` stopped the recording: closes the open bag at its last flush
    /// ([`BagWriter::abandon`]), writes metadata.yaml for what the bags keep (both as far as
    /// the disk allows, failures logged) and returns [`RecordError::Lost`] naming the bag;
    /// `error` itself when no bag was open.
    fn salvage(&mut self, error: RecordError) -> RecordError {
        let Some(bag) = self.bag.take() else {
            return error;
        };
        let (path, kept) = (bag.info.path.clone(), bag.flushed.count);
        let lost = bag.info.count - kept;
        match bag.writer.abandon() {
            Ok(bytes) => tracing::warn!(
                "{}: closed at its last flush ({bytes} bytes, {kept} frames)",
                path.display()
            ),
            Err(e) => tracing::warn!("{e}; the bag ends at its last flush without a footer"),
        }
        if kept > 0 {
            self.report.files.push(path.clone());
            self.infos.push(bag.flushed);
        }
        if let Err(e) = write_metadata(&self.options.out, &self.infos) {
            tracing::warn!("{e}");
        }
        RecordError::Lost {
            path,
            kept,
            lost,
            source: Box::new(error),
        }
    }
}

/// Closes and flushes `bag`'s current chunk when `every` passed since `last`.
fn flush_if_due(
    bag: &mut Option<OpenBag>,
    last: &mut Instant,
    every: Duration,
) -> Result<(), RecordError> {
    if last.elapsed() < every {
        return Ok(());
    }
    *last = Instant::now();
    if let Some(b) = bag {
        if b.pending > 0 {
            b.writer.flush()?;
            b.pending = 0;
            b.flushed = b.info.clone();
        }
    }
    Ok(())
}

/// Finishes `bag`, adding its path to the report's files.
fn close(bag: OpenBag, report: &mut RecordReport) -> Result<FileInfo, RecordError> {
    bag.writer.finish()?;
    report.files.push(bag.info.path.clone());
    Ok(bag.info)
}
