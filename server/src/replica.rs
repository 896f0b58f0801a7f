//! Storage shared by several servers: every commit of the embedded store
//! (`store.rs`: a session's description and camera, its new poses, its new
//! keyframe records, its changed map blocks) is copied to PostgreSQL
//! (`store.replica_url`), which outlives any one server.
//!
//! Why PostgreSQL: a real database every operator can run, back up and replicate
//! on its own (streaming replication, managed services), transactional (a commit
//! is all there or none of it), queryable by other tools; the sessions' data are
//! a few keyed tables, which it holds well. The embedded redb store stays each
//! server's own and the default for one server; the replica is a copy.
//!
//! The copy runs on a thread of its own behind a bounded queue
//! (`store.replica_queue` commits): the map lane hands a commit over and goes on.
//! A commit finding the queue full is not copied (counted in
//! `stillmap_replica_dropped_total`, logged); the server's own store still has
//! it. While PostgreSQL cannot be reached the thread reconnects every
//! 1 s, doubling up to 30 s, and retries the commit it holds.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::time::{Duration, Instant};

use prometheus_client::metrics::counter::Counter;

/// What one commit wrote to the embedded store, ready to copy.
#[derive(Debug, Clone, Default)]
pub struct ReplicaCommit {
    pub session_id: String,
    /// The session's description (`SessionMeta`, JSON).
    pub meta_json: Vec<u8>,
    /// The session's camera (`CameraInfo`, protobuf), with its first commit.
    pub camera: Option<Vec<u8>>,
    /// New poses: place in the trajectory and `PoseStamped` (protobuf).
    pub poses: Vec<(u64, Vec<u8>)>,
    /// New keyframe records: id and bytes (the store's encoding).
    pub keyframes: Vec<(u64, Vec<u8>)>,
    /// Changed map blocks: key and zstd-compressed bytes (the store's encoding).
    pub blocks: Vec<([i32; 3], Vec<u8>)>,
    /// SHA-256 of the session's resume secret, with its first commit (a robot
    /// presents the secret to resume the session on another server).
    pub resume_secret_sha256: Option<Vec<u8>>,
    /// The session's frame in its fleet (`FleetFrame`, JSON), when it has one: a
    /// server resuming the session brings its merge along.
    pub fleet_frame: Option<Vec<u8>>,
}

impl ReplicaCommit {
    /// Bytes this commit copies.
    pub fn bytes(&self) -> usize {
        self.meta_json.len()
            + self.camera.as_ref().map_or(0, Vec::len)
            + self.poses.iter().map(|(_, p)| p.len()).sum::<usize>()
            + self.keyframes.iter().map(|(_, k)| k.len()).sum::<usize>()
            + self.blocks.iter().map(|(_, b)| b.len()).sum::<usize>()
    }
}

/// What the copy thread does next, in the order it was handed over.
#[derive(Debug)]
enum ReplicaJob {
    Commit(ReplicaCommit),
    /// Session `id` left this server for another (its robot was placed there): its
    /// row names no writer from now on, so the new owner may take it over. Queued
    /// behind the session's last commits.
    Release(String),
    /// Session `id`'s frame in its fleet changed (JSON), while this server writes it.
    FleetFrame(String, Vec<u8>),
    /// Sessions' shares of their fleets' pose graphs are waiting
    /// ([`Replica::fleet_graph`]): the latest of each is written, while this
    /// server writes the session.
    FleetGraphs,
    /// The shares taken from the waiting ones, by session id (made by the thread).
    FleetGraphsTaken(Vec<(String, String)>),
}

impl ReplicaJob {
    fn session_id(&self) -> &str {
        match self {
            Self::Commit(c) => &c.session_id,
            Self::Release(id) | Self::FleetFrame(id, _) => id,
            Self::FleetGraphs | Self::FleetGraphsTaken(_) => "(pose-graph shares)",
        }
    }
}

/// The replica's counters (registered in `/metrics`).
#[derive(Debug, Clone, Default)]
pub struct ReplicaCounters {
    pub commits: Counter,
    pub bytes: Counter,
    pub dropped: Counter,
    /// Commits not written because another server writes the session now.
    pub fenced: Counter,
    /// Time spent writing commits, in microseconds.
    pub write_micros: Counter,
}

/// The tables, created when missing. Keys are the store's; values its encodings.
/// A pose's `sequence` column is its place in the session's trajectory (the order
/// poses came; stores before 2026-12-07 wrote the robot's sequence number, which
/// starts again when a robot's timeline is taken again and so overwrote poses).
pub const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS stillmap_sessions (
    id text PRIMARY KEY,
    server_id text NOT NULL,
    meta jsonb NOT NULL,
    camera bytea,
    updated timestamptz NOT NULL DEFAULT now()
);
ALTER TABLE stillmap_sessions ADD COLUMN IF NOT EXISTS resume_secret_sha256 bytea;
ALTER TABLE stillmap_sessions ADD COLUMN IF NOT EXISTS fleet_frame jsonb;
ALTER TABLE stillmap_sessions ADD COLUMN IF NOT EXISTS fleet_graph jsonb;
CREATE TABLE IF NOT EXISTS stillmap_poses (
    session_id text NOT NULL,
    sequence bigint NOT NULL,
    pose bytea NOT NULL,
    PRIMARY KEY (session_id, sequence)
);
CREATE TABLE IF NOT EXISTS stillmap_keyframes (
    session_id text NOT NULL,
    id bigint NOT NULL,
    record bytea NOT NULL,
    PRIMARY KEY (session_id, id)
);
CREATE TABLE IF NOT EXISTS stillmap_blocks (
    session_id text NOT NULL,
    x integer NOT NULL,
    y integer NOT NULL,
    z integer NOT NULL,
    block bytea NOT NULL,
    PRIMARY KEY (session_id, x, y, z)
);
";

#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    #[error("store.replica_url: {0}")]
    Url(String),
    #[error("cannot start the replica thread: {0}")]
    Thread(std::io::Error),
    #[error("shared storage: {0}")]
    Read(String),
    #[error("shared storage holds a damaged session: {0}")]
    Corrupt(String),
}

/// A session as the shared storage holds it, to resume on this server: its
/// description, camera, trajectory, latest keyframe records and map blocks.
pub enum ReplicaSession {
    /// The storage does not hold it.
    Absent,
    /// It holds it, for another robot or with another resume secret (nothing more is read).
    Refused(String),
    /// It holds it, last written by the server `server_id`.
    /// Its frame in its fleet and its share of the fleet's pose graph come along
    /// when it has them (an unreadable one is left out, logged).
    Found {
        session: Box<crate::store::StoredSession>,
        server_id: String,
        fleet_frame: Option<crate::store::FleetFrame>,
        fleet_graph: Option<Box<crate::store::SessionGraph>>,
    },
}

/// The older keyframe records of a session resumed from the shared storage (which
/// gives the resume only its newest few), read back in the background.
pub struct Backfill {
    pub session_id: String,
    /// The records with a smaller id are read.
    pub before_id: u64,
    /// Given each page of records, newest first; false stops the reading.
    pub page: Box<dyn FnMut(Vec<crate::store::KeyframeRecord>) -> bool + Send>,
}

/// Sessions remembered as fenced off (for logging each once); forgotten beyond it.
const MAX_FENCED_LOGGED: usize = 4096;
/// Keyframe records read back per query (about 50 KB each).
const BACKFILL_PAGE: usize = 32;
/// Backfills waiting for the thread; more are left out (logged).
const BACKFILL_QUEUE: usize = 256;
/// Sessions whose pose-graph share waits to be written; a share of another one
/// beyond it is left out (logged; the next solve brings it again).
const MAX_WAITING_SHARES: usize = 4096;

/// SHA-256 of a resume secret, as the shared storage keeps it.
pub fn secret_hash(secret: &str) -> Vec<u8> {
    use sha2::Digest as _;
    sha2::Sha256::digest(secret.as_bytes()).to_vec()
}

/// The copy to PostgreSQL: a bounded queue and the thread that empties it.
pub struct Replica {
    /// Where PostgreSQL is (sessions are read back with connections of their own).
    config: postgres::Config,
    jobs: std::sync::Mutex<Option<SyncSender<ReplicaJob>>>,
    counters: ReplicaCounters,
    /// Told when the thread has finished (it is never joined: a stuck connection
    /// must not hold the server's shutdown).
    done: std::sync::Mutex<Receiver<()>>,
    /// The server whose commits these are (its cluster id once known).
    server_id: Arc<std::sync::Mutex<String>>,
    /// Set at shutdown: the thread copies what is queued while PostgreSQL answers,
    /// and stops retrying when it does not.
    closing: Arc<AtomicBool>,
    /// What every commit of a session carries, by session id (a commit left out
    /// must not leave the session impossible to resume, or without its merge).
    carried: std::sync::Mutex<std::collections::HashMap<String, Carried>>,
    /// The latest pose-graph share of each session not written yet (JSON), and
    /// whether a job to write them is queued: a solve replaces what an earlier one
    /// left waiting, so shares never take more than one queue slot.
    shares: Shares,
    shares_queued: Arc<AtomicBool>,
    /// The backfill thread's queue (see [`Backfill`]).
    backfills: std::sync::Mutex<Option<SyncSender<Backfill>>>,
}

/// Whether the copy thread took a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Queued {
    Yes,
    /// `store.replica_queue` jobs wait already.
    Full,
    /// The replica is closing.
    Closed,
}

/// What each commit of a session carries once known.
#[derive(Debug, Default)]
struct Carried {
    /// The resume secret's SHA-256.
    secret_sha256: Option<Vec<u8>>,
    /// Its frame in its fleet (`FleetFrame`, JSON).
    fleet_frame: Option<Vec<u8>>,
}

/// Longest wait for a connection, and for one statement (a stalled peer must not
/// hold the thread for ever).
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
const STATEMENT_TIMEOUT_MS: u32 = 30_000;
/// Longest wait between attempts while PostgreSQL fails.
const MAX_RETRY_WAIT: Duration = Duration::from_secs(30);
/// A commit PostgreSQL itself refuses (a permission, a full disk, another schema)
/// is tried this many times, then left out (counted as dropped).
const REFUSED_ATTEMPTS: u32 = 5;
/// At shutdown, how long the queued commits may take to be copied.
const CLOSE_WAIT: Duration = Duration::from_secs(10);

impl Replica {
    /// Parses `url` (a libpq URL or key=value string; checked now, connected to on
    /// the thread) and starts the thread copying this server's commits, at most
    /// `queue` waiting.
    pub fn start(url: &str, queue: usize, counters: ReplicaCounters) -> Result<Arc<Self>, ReplicaError> {
        let mut config: postgres::Config = url.parse().map_err(|e: postgres::Error| ReplicaError::Url(e.to_string()))?;
        config
            .connect_timeout(CONNECT_TIMEOUT)
            .keepalives(true)
            .keepalives_idle(Duration::from_secs(30))
            .keepalives_interval(Duration::from_secs(10))
            .keepalives_retries(3)
            .options(&format!("-c statement_timeout={STATEMENT_TIMEOUT_MS}"));
        let (tx, rx) = std::sync::mpsc::sync_channel(queue.max(1));
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let server_id = Arc::new(std::sync::Mutex::new(String::new()));
        let closing = Arc::new(AtomicBool::new(false));
        let (worker_id, worker_counters, worker_closing, worker_config) =
            (server_id.clone(), counters.clone(), closing.clone(), config.clone());
        let shares = Shares::default();
        let shares_queued = Arc::new(AtomicBool::new(false));
        let waiting = (shares.clone(), shares_queued.clone());
        std::thread::Builder::new()
            .name("replica".into())
            .spawn(move || {
                copy(worker_config, &worker_id, rx, &worker_counters, &worker_closing, &waiting);
                let _ = done_tx.send(());
            })
            .map_err(ReplicaError::Thread)?;
        let (backfill_tx, backfill_rx) = std::sync::mpsc::sync_channel(BACKFILL_QUEUE);
        let (backfill_config, backfill_closing) = (config.clone(), closing.clone());
        std::thread::Builder::new()
            .name("replica-backfill".into())
            .spawn(move || backfill(&backfill_config, backfill_rx, &backfill_closing))
            .map_err(ReplicaError::Thread)?;
        let done = std::sync::Mutex::new(done_rx);
        let carried = std::sync::Mutex::default();
        let backfills = std::sync::Mutex::new(Some(backfill_tx));
        Ok(Arc::new(Self {
            config,
            jobs: std::sync::Mutex::new(Some(tx)),
            counters,
            done,
            server_id,
            closing,
            carried,
            shares,
            shares_queued,
            backfills,
        }))
    }

    /// Reads session `id` back from PostgreSQL (its newest `keyframes` records) for
    /// robot `robot_id` presenting `resume_secret`, on a thread and a connection of
    /// its own. Its description is read first: the rest only for its own robot with
    /// its secret.
    pub fn load(&self, id: &str, robot_id: &str, resume_secret: &str, keyframes: usize) -> Result<ReplicaSession, ReplicaError> {
        let (config, id, robot_id, secret) = (self.config.clone(), id.to_string(), robot_id.to_string(), secret_hash(resume_secret));
        let presented = !resume_secret.is_empty();
        on_own_thread("replica-read", "reading", move || {
            read_session(&config, &id, &robot_id, presented.then_some(secret.as_slice()), keyframes)
        })
    }

    /// The server that last wrote each of `ids` that PostgreSQL holds, on a thread and
    /// a connection of its own.
    pub fn writers(&self, ids: &[String]) -> Result<std::collections::HashMap<String, String>, ReplicaError> {
        let (config, ids) = (self.config.clone(), ids.to_vec());
        on_own_thread("replica-writers", "reading", move || {
            let read = |e: postgres::Error| ReplicaError::Read(describe(&e));
            let mut client = config.connect(postgres::NoTls).map_err(read)?;
            let rows = client.query("SELECT id, server_id FROM stillmap_sessions WHERE id = ANY($1)", &[&ids]).map_err(read)?;
            Ok(rows.iter().map(|r| (r.get::<_, String>(0), r.get::<_, String>(1))).collect())
        })
    }

    /// Takes session `id` over from server `writer`, its last writer, in one
    /// statement: true when this server writes it from now on, false when another
    /// server took it first (two servers never resume one session).
    pub fn claim(&self, id: &str, writer: &str) -> Result<bool, ReplicaError> {
        let (config, id, writer, me) = (self.config.clone(), id.to_string(), writer.to_string(), crate::lock(&self.server_id).clone());
        on_own_thread("replica-claim", "claiming", move || {
            let mut client = config.connect(postgres::NoTls).map_err(|e| ReplicaError::Read(describe(&e)))?;
            let n = client
                .execute("UPDATE stillmap_sessions SET server_id = $1 WHERE id = $2 AND server_id = $3", &[&me, &id, &writer])
                .map_err(|e| ReplicaError::Read(describe(&e)))?;
            Ok(n == 1)
        })
    }

    /// Sends `hash` (its resume secret's) with every later commit of session `session_id`.
    pub fn remember(&self, session_id: &str, hash: Vec<u8>) {
        crate::lock(&self.carried).entry(session_id.to_string()).or_default().secret_sha256 = Some(hash);
    }

    /// Forgets what a session's commits carry once the session left this server's
    /// memory (PostgreSQL has it).
    pub fn forget(&self, session_id: &str) {
        crate::lock(&self.carried).remove(session_id);
    }

    /// Copies session `session_id`'s frame in its fleet (`FleetFrame` as JSON) now,
    /// where PostgreSQL already holds the session, and with every later commit of it.
    pub fn fleet_frame(&self, session_id: &str, json: Vec<u8>) {
        crate::lock(&self.carried).entry(session_id.to_string()).or_default().fleet_frame = Some(json.clone());
        if self.enqueue(ReplicaJob::FleetFrame(session_id.to_string(), json)) == Queued::Full {
            tracing::warn!(session = session_id, "replica queue full (store.replica_queue): the fleet frame goes with the next commit");
        }
    }

    /// Copies session `session_id`'s share of its fleet's pose graph
    /// (`SessionGraph` as JSON) after a solve, where PostgreSQL holds the session
    /// and this server writes it. Only the latest share of a session waits; one
    /// queued job writes every waiting share (when the queue is full, the next
    /// share handed over queues it).
    pub fn fleet_graph(&self, session_id: &str, json: String) {
        {
            let mut waiting = crate::lock(&self.shares);
            if waiting.len() >= MAX_WAITING_SHARES && !waiting.contains_key(session_id) {
                tracing::warn!(session = session_id, "{MAX_WAITING_SHARES} pose-graph shares wait for PostgreSQL: this one is left out");
                return;
            }
            waiting.insert(session_id.to_string(), json);
        }
        if !self.shares_queued.swap(true, Ordering::SeqCst) && self.enqueue(ReplicaJob::FleetGraphs) != Queued::Yes {
            self.shares_queued.store(false, Ordering::SeqCst);
        }
    }

    /// Hands a job to the copy thread without waiting.
    fn enqueue(&self, job: ReplicaJob) -> Queued {
        let Some(tx) = crate::lock(&self.jobs).clone() else { return Queued::Closed };
        match tx.try_send(job) {
            Ok(()) => Queued::Yes,
            Err(TrySendError::Full(_)) => Queued::Full,
            Err(TrySendError::Disconnected(_)) => Queued::Closed,
        }
    }

    /// Names the server in the rows it writes from now on (`stillmap_sessions.server_id`).
    pub fn name_server(&self, id: &str) {
        *crate::lock(&self.server_id) = id.to_string();
    }

    /// Reads a resumed session's older keyframe records back in the background, on
    /// a thread and a connection of its own, a page at a time; a full queue leaves
    /// them out (logged: the session goes on without them here).
    pub fn backfill(&self, job: Backfill) {
        let Some(tx) = crate::lock(&self.backfills).clone() else { return };
        match tx.try_send(job) {
            Ok(()) => {}
            Err(TrySendError::Full(job)) => {
                tracing::warn!(session = %job.session_id, "replica: too many resumed sessions wait for their older keyframes; this one's are not read back");
            }
            Err(TrySendError::Disconnected(job)) => {
                tracing::error!(session = %job.session_id, "replica: the thread reading older keyframes back has stopped (a bug); not read back");
            }
        }
    }

    /// Hands a commit to the copy; a full queue leaves it out (counted, logged).
    pub fn submit(&self, mut commit: ReplicaCommit) {
        {
            let mut carried = crate::lock(&self.carried);
            let carried = carried.entry(commit.session_id.clone()).or_default();
            match &commit.resume_secret_sha256 {
                Some(hash) => carried.secret_sha256 = Some(hash.clone()),
                None => commit.resume_secret_sha256.clone_from(&carried.secret_sha256),
            }
            if commit.fleet_frame.is_none() {
                commit.fleet_frame.clone_from(&carried.fleet_frame);
            }
        }
        let id = commit.session_id.clone();
        if self.enqueue(ReplicaJob::Commit(commit)) == Queued::Full {
            self.counters.dropped.inc();
            tracing::warn!(session = %id, "replica queue full (store.replica_queue): this commit is not copied to PostgreSQL");
        }
    }

    /// Lets another server take session `id` over: once the commits queued before
    /// it are copied, its row names no writer (`server_id = ''`, where it still
    /// names this server), and a server resuming it claims it from there. Call it
    /// after the session's last commit (it left memory). False when it cannot be
    /// queued (the queue full, or the replica closing): the session stays this
    /// server's, and a robot resuming it elsewhere gets a new session.
    pub fn release(&self, id: &str) -> bool {
        match self.enqueue(ReplicaJob::Release(id.to_string())) {
            Queued::Yes => true,
            Queued::Full => {
                tracing::warn!(session = id, "replica queue full (store.replica_queue): the session is not handed over");
                false
            }
            Queued::Closed => false,
        }
    }

    /// At shutdown: copies what is queued, waiting at most `CLOSE_WAIT`; while
    /// PostgreSQL fails, what is queued is left (counted as dropped).
    pub fn close(&self) {
        self.closing.store(true, Ordering::SeqCst);
        crate::lock(&self.backfills).take();
        crate::lock(&self.jobs).take();
        if crate::lock(&self.done).recv_timeout(CLOSE_WAIT).is_err() {
            tracing::warn!("replica: the copy to PostgreSQL did not finish within {CLOSE_WAIT:?} of shutdown; left behind");
        }
    }
}

/// Waits `wait` in short steps, returning early when the server shuts down.
fn pause(wait: Duration, closing: &AtomicBool) {
    let until = Instant::now() + wait;
    while Instant::now() < until && !closing.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The latest pose-graph share (JSON) of each session waiting to be written.
type Shares = Arc<std::sync::Mutex<std::collections::HashMap<String, String>>>;

/// The waiting pose-graph shares and whether a job to write them is queued (see [`Replica`]).
type WaitingShares = (Shares, Arc<AtomicBool>);

/// The replica thread: connects (again, with a growing wait, while it fails) and
/// writes each commit in one transaction, until the queue closes. At shutdown,
/// a failure ends it (what is left is counted as dropped).
fn copy(
    config: postgres::Config,
    server_id: &std::sync::Mutex<String>,
    rx: Receiver<ReplicaJob>,
    counters: &ReplicaCounters,
    closing: &AtomicBool,
    (shares, shares_queued): &WaitingShares,
) {
    let mut client: Option<postgres::Client> = None;
    let mut wait = Duration::from_secs(1);
    // Sessions whose commits another server's claim fenced off (logged once each).
    let mut fenced = std::collections::HashSet::new();
    let give_up = |left: u64| {
        counters.dropped.inc_by(left);
        tracing::warn!(left, "replica: PostgreSQL fails at shutdown; these commits are not copied");
    };
    for job in rx.iter() {
        let job = match job {
            ReplicaJob::FleetGraphs => {
                shares_queued.store(false, Ordering::SeqCst);
                let taken: Vec<(String, String)> = std::mem::take(&mut *crate::lock(shares)).into_iter().collect();
                if taken.is_empty() {
                    continue;
                }
                ReplicaJob::FleetGraphsTaken(taken)
            }
            other => other,
        };
        let mut refused = 0;
        loop {
            if client.is_none() {
                match config.connect(postgres::NoTls).and_then(|mut c| c.batch_execute(SCHEMA).map(|()| c)) {
                    Ok(c) => {
                        tracing::info!("replica: connected to PostgreSQL");
                        client = Some(c);
                    }
                    Err(e) => {
                        if closing.load(Ordering::SeqCst) {
                            return give_up(1 + rx.try_iter().count() as u64);
                        }
                        tracing::warn!("replica: PostgreSQL cannot be reached ({}); again in {} s", describe(&e), wait.as_secs());
                        pause(wait, closing);
                        wait = (wait * 2).min(MAX_RETRY_WAIT);
                        continue;
                    }
                }
            }
            let Some(c) = client.as_mut() else { continue };
            let started = Instant::now();
            let server = crate::lock(server_id).clone();
            let written = match &job {
                ReplicaJob::Commit(commit) => write(c, &server, commit),
                ReplicaJob::Release(id) => {
                    c.execute("UPDATE stillmap_sessions SET server_id = '' WHERE id = $1 AND server_id = $2", &[id, &server]).map(|_| true)
                }
                ReplicaJob::FleetFrame(id, json) => {
                    let json = std::str::from_utf8(json).unwrap_or("null");
                    c.execute(
                        "UPDATE stillmap_sessions SET fleet_frame = $3::text::jsonb WHERE id = $1 AND server_id = $2",
                        &[id, &server, &json],
                    )
                    .map(|_| true)
                }
                ReplicaJob::FleetGraphsTaken(taken) => write_shares(c, &server, taken),
                // Turned into FleetGraphsTaken above, before the first try.
                ReplicaJob::FleetGraphs => Ok(true),
            };
            match written {
                Ok(copied) => {
                    if let ReplicaJob::Commit(commit) = &job {
                        if copied {
                            counters.commits.inc();
                            counters.bytes.inc_by(commit.bytes() as u64);
                            counters.write_micros.inc_by(started.elapsed().as_micros() as u64);
                        } else {
                            counters.fenced.inc();
                            if fenced.len() >= MAX_FENCED_LOGGED {
                                fenced.clear();
                            }
                            if fenced.insert(commit.session_id.clone()) {
                                tracing::warn!(
                                    session = %commit.session_id,
                                    "replica: another server has taken this session over; this server's commits to it are left out"
                                );
                            }
                        }
                    }
                    wait = Duration::from_secs(1);
                    break;
                }
                Err(e) => {
                    // Refused by PostgreSQL itself: the same commit is likely refused
                    // again; a few tries, then it is left out.
                    refused += u32::from(e.as_db_error().is_some());
                    if refused >= REFUSED_ATTEMPTS {
                        if matches!(job, ReplicaJob::Commit(_)) {
                            counters.dropped.inc();
                        }
                        tracing::error!(session = %job.session_id(), "replica: PostgreSQL refuses this write ({}); left out", describe(&e));
                        break;
                    }
                    if closing.load(Ordering::SeqCst) {
                        return give_up(1 + rx.try_iter().count() as u64);
                    }
                    tracing::warn!(session = %job.session_id(), "replica: commit not written ({}); again in {} s", describe(&e), wait.as_secs());
                    client = None;
                    pause(wait, closing);
                    wait = (wait * 2).min(MAX_RETRY_WAIT);
                }
            }
        }
    }
}

/// Writes pose-graph shares in one transaction, each only where this server
/// writes the session (not one that moved to another server since).
fn write_shares(c: &mut postgres::Client, server: &str, taken: &[(String, String)]) -> Result<bool, postgres::Error> {
    let mut tx = c.transaction()?;
    for (id, json) in taken {
        tx.execute("UPDATE stillmap_sessions SET fleet_graph = $3::text::jsonb WHERE id = $1 AND server_id = $2", &[id, &server, &json])?;
    }
    tx.commit()?;
    Ok(true)
}

/// Runs `f` on a thread named `name` (a connection of its own, off the caller's
/// runtime) and waits for it; a panic there is a read error naming `doing`.
fn on_own_thread<T: Send + 'static>(
    name: &str,
    doing: &str,
    f: impl FnOnce() -> Result<T, ReplicaError> + Send + 'static,
) -> Result<T, ReplicaError> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(ReplicaError::Thread)?
        .join()
        .map_err(|_| ReplicaError::Read(format!("the {doing} thread panicked")))?
}

/// The backfill thread: pages through each job's older keyframe records, on one
/// connection (made again after a failure), until the queue closes; at shutdown
/// what is queued is dropped.
fn backfill(config: &postgres::Config, jobs: Receiver<Backfill>, closing: &AtomicBool) {
    use crate::store::KeyframeRecord;
    let mut client: Option<postgres::Client> = None;
    let page = i64::try_from(BACKFILL_PAGE).unwrap_or(i64::MAX);
    for mut job in jobs {
        let (id, mut before, mut read) = (job.session_id.clone(), job.before_id, 0usize);
        while !closing.load(Ordering::SeqCst) {
            if client.is_none() {
                match config.connect(postgres::NoTls) {
                    Ok(c) => client = Some(c),
                    Err(e) => {
                        tracing::warn!(session = %id, "replica: older keyframes not read back (PostgreSQL: {})", describe(&e));
                        break;
                    }
                }
            }
            let Some(c) = client.as_mut() else { break };
            let below = i64::try_from(before).unwrap_or(i64::MAX);
            let rows = match c.query(
                "SELECT record FROM stillmap_keyframes WHERE session_id = $1 AND id < $2 ORDER BY id DESC LIMIT $3",
                &[&id, &below, &page],
            ) {
                Ok(rows) => rows,
                Err(e) => {
                    tracing::warn!(session = %id, "replica: older keyframes not read back (PostgreSQL: {})", describe(&e));
                    client = None;
                    break;
                }
            };
            let records: Result<Vec<KeyframeRecord>, _> = rows.iter().map(|r| KeyframeRecord::from_bytes(r.get::<_, &[u8]>(0))).collect();
            let records = match records {
                Ok(records) => records,
                Err(e) => {
                    tracing::warn!(session = %id, "replica: a damaged keyframe record stops reading the older ones back: {e}");
                    break;
                }
            };
            let Some(oldest) = records.iter().map(|k| k.id).min() else { break };
            let full = records.len() == BACKFILL_PAGE;
            read += records.len();
            before = oldest;
            if !(job.page)(records) || !full {
                break;
            }
        }
        if read > 0 {
            tracing::info!(session = %id, keyframes = read, "older keyframe records read back from the shared storage");
        }
    }
}

/// Session `id` as PostgreSQL holds it.
fn read_session(
    config: &postgres::Config,
    id: &str,
    robot_id: &str,
    secret_sha256: Option<&[u8]>,
    keyframes: usize,
) -> Result<ReplicaSession, ReplicaError> {
    use crate::store::{KeyframeRecord, SessionMeta, StoredSession, decode_block};
    use prost::Message as _;
    let read = |e: postgres::Error| ReplicaError::Read(describe(&e));
    let corrupt = |what: &str, e: &dyn std::fmt::Display| ReplicaError::Corrupt(format!("session {id} {what}: {e}"));
    let mut client = config.connect(postgres::NoTls).map_err(read)?;
    let Some(row) = client
        .query_opt(
            "SELECT meta::text, camera, resume_secret_sha256, server_id, fleet_frame::text, fleet_graph::text FROM stillmap_sessions WHERE id = $1",
            &[&id],
        )
        .map_err(read)?
    else {
        return Ok(ReplicaSession::Absent);
    };
    let meta: SessionMeta = serde_json::from_str(row.get::<_, &str>(0)).map_err(|e| corrupt("description", &e))?;
    if meta.robot_id != robot_id {
        return Ok(ReplicaSession::Refused(format!("session {id} belongs to robot {:?}, not {robot_id:?}", meta.robot_id)));
    }
    let held: Option<&[u8]> = row.get(2);
    if !held.zip(secret_sha256).is_some_and(|(held, given)| crate::auth::same_secret_bytes(held, given)) {
        return Ok(ReplicaSession::Refused(format!(
            "resuming session {id} needs the resume secret its accept returned (Hello.resume_secret)"
        )));
    }
    let camera: Option<Vec<u8>> = row.get(1);
    let camera = pb_camera(camera.as_deref()).map_err(|e| corrupt("camera", &e))?;
    let server_id: String = row.get(3);
    let fleet_frame = row.get::<_, Option<&str>>(4).and_then(|json| {
        serde_json::from_str::<crate::store::FleetFrame>(json)
            .inspect_err(|e| {
                tracing::warn!(session = id, "its fleet frame in the shared storage is unreadable (merged again instead): {e}")
            })
            .ok()
    });
    let fleet_graph = row.get::<_, Option<&str>>(5).and_then(|json| {
        serde_json::from_str::<Box<crate::store::SessionGraph>>(json)
            .inspect_err(|e| tracing::warn!(session = id, "its pose-graph share in the shared storage is unreadable (left out): {e}"))
            .ok()
    });
    let (mut poses, mut next_pose_place) = (Vec::new(), 0u64);
    for r in client.query("SELECT sequence, pose FROM stillmap_poses WHERE session_id = $1 ORDER BY sequence", &[&id]).map_err(read)? {
        next_pose_place = crate::store::next_place_after(next_pose_place, r.get::<_, i64>(0) as u64);
        poses.push(stillmap_proto::pb::PoseStamped::decode(r.get::<_, &[u8]>(1)).map_err(|e| corrupt("pose", &e))?);
    }
    let limit = i64::try_from(keyframes).unwrap_or(i64::MAX);
    let mut records = Vec::new();
    for r in client
        .query("SELECT record FROM stillmap_keyframes WHERE session_id = $1 ORDER BY id DESC LIMIT $2", &[&id, &limit])
        .map_err(read)?
    {
        records.push(KeyframeRecord::from_bytes(r.get::<_, &[u8]>(0)).map_err(|e| corrupt("keyframe", &e))?);
    }
    records.reverse();
    let mut blocks = Vec::new();
    for r in client.query("SELECT x, y, z, block FROM stillmap_blocks WHERE session_id = $1", &[&id]).map_err(read)? {
        let key = crate::store::checked_block_key([r.get::<_, i32>(0), r.get::<_, i32>(1), r.get::<_, i32>(2)])
            .map_err(|e| corrupt("map block", &e))?;
        blocks.push((key, decode_block(r.get::<_, &[u8]>(3)).map_err(|e| corrupt("map block", &e))?));
    }
    let session = Box::new(StoredSession { id: id.to_string(), meta, camera, poses, next_pose_place, keyframes: records, blocks });
    Ok(ReplicaSession::Found { session, server_id, fleet_frame, fleet_graph })
}

fn pb_camera(bytes: Option<&[u8]>) -> Result<stillmap_proto::pb::CameraInfo, String> {
    use prost::Message as _;
    let bytes = bytes.ok_or("missing")?;
    stillmap_proto::pb::CameraInfo::decode(bytes).map_err(|e| e.to_string())
}

/// An error with PostgreSQL's own message when it has one (its Display says only "db error").
fn describe(e: &postgres::Error) -> String {
    match e.as_db_error() {
        Some(db) => format!("{} {}", db.code().code(), db.message()),
        None => e.to_string(),
    }
}

/// One commit, in one transaction (upserts: a commit sent twice changes nothing).
/// Fenced: written only while the row names this server or no writer (a handover's
/// release); once another server has taken the session over (`Replica::claim`), a
/// commit still queued here changes nothing and `Ok(false)` says so.
fn write(client: &mut postgres::Client, server_id: &str, c: &ReplicaCommit) -> Result<bool, postgres::Error> {
    let mut tx = client.transaction()?;
    let meta = std::str::from_utf8(&c.meta_json).unwrap_or("{}");
    let fleet_frame = c.fleet_frame.as_deref().and_then(|f| std::str::from_utf8(f).ok());
    let rows = tx.execute(
        "INSERT INTO stillmap_sessions (id, server_id, meta, camera, resume_secret_sha256, fleet_frame)
             VALUES ($1, $2, $3::text::jsonb, $4, $5, $6::text::jsonb)
         ON CONFLICT (id) DO UPDATE SET server_id = $2, meta = $3::text::jsonb,
             camera = COALESCE($4, stillmap_sessions.camera),
             resume_secret_sha256 = COALESCE($5, stillmap_sessions.resume_secret_sha256),
             fleet_frame = COALESCE($6::text::jsonb, stillmap_sessions.fleet_frame), updated = now()
         WHERE stillmap_sessions.server_id IN ($2, '')",
        &[&c.session_id, &server_id, &meta, &c.camera, &c.resume_secret_sha256, &fleet_frame],
    )?;
    if rows == 0 {
        // Dropped: rolled back.
        return Ok(false);
    }
    // One statement per table, the rows as arrays (one round trip each).
    if !c.poses.is_empty() {
        let sequences: Vec<i64> = c.poses.iter().map(|(s, _)| *s as i64).collect();
        let poses: Vec<&[u8]> = c.poses.iter().map(|(_, p)| p.as_slice()).collect();
        tx.execute(
            "INSERT INTO stillmap_poses (session_id, sequence, pose) SELECT $1, * FROM unnest($2::bigint[], $3::bytea[])
             ON CONFLICT (session_id, sequence) DO UPDATE SET pose = excluded.pose",
            &[&c.session_id, &sequences, &poses],
        )?;
    }
    if !c.keyframes.is_empty() {
        let ids: Vec<i64> = c.keyframes.iter().map(|(id, _)| *id as i64).collect();
        let records: Vec<&[u8]> = c.keyframes.iter().map(|(_, r)| r.as_slice()).collect();
        tx.execute(
            "INSERT INTO stillmap_keyframes (session_id, id, record) SELECT $1, * FROM unnest($2::bigint[], $3::bytea[])
             ON CONFLICT (session_id, id) DO UPDATE SET record = excluded.record",
            &[&c.session_id, &ids, &records],
        )?;
    }
    if !c.blocks.is_empty() {
        // A key once per statement (PostgreSQL refuses to update a row twice in one): the last wins.
        let mut latest: Vec<&([i32; 3], Vec<u8>)> = Vec::with_capacity(c.blocks.len());
        let mut seen = std::collections::HashSet::with_capacity(c.blocks.len());
        for b in c.blocks.iter().rev() {
            if seen.insert(b.0) {
                latest.push(b);
            }
        }
        let axis = |i: usize| -> Vec<i32> { latest.iter().map(|(k, _)| k[i]).collect() };
        let blocks: Vec<&[u8]> = latest.iter().map(|(_, b)| b.as_slice()).collect();
        tx.execute(
            "INSERT INTO stillmap_blocks (session_id, x, y, z, block)
             SELECT $1, * FROM unnest($2::integer[], $3::integer[], $4::integer[], $5::bytea[])
             ON CONFLICT (session_id, x, y, z) DO UPDATE SET block = excluded.block",
            &[&c.session_id, &axis(0), &axis(1), &axis(2), &blocks],
        )?;
    }
    tx.commit().map(|()| true)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A URL that is not one is refused by name before anything starts.
    #[test]
    fn a_bad_url_is_refused_at_start() {
        let err = Replica::start("postgresql://[::1", 4, ReplicaCounters::default()).err().expect("refused");
        assert!(err.to_string().starts_with("store.replica_url: "), "{err}");
    }

    #[test]
    fn a_commit_counts_its_bytes() {
        let c = ReplicaCommit {
            session_id: "s".into(),
            meta_json: b"{}".to_vec(),
            camera: Some(vec![0; 3]),
            poses: vec![(1, vec![0; 10])],
            keyframes: vec![(1, vec![0; 100])],
            blocks: vec![([0, 0, 0], vec![0; 1000])],
            resume_secret_sha256: None,
            fleet_frame: None,
        };
        assert_eq!(c.bytes(), 2 + 3 + 10 + 100 + 1000);
    }
}
