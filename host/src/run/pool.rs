//! The threads that run the core's parallel work ([`loglio_core::parallel`]).
//!
//! A scan hands out five or six batches of jobs (the undistortion, Ring FALS beside the voxel
//! search, the moving points, the association's searches, the free-space judgements), each
//! 0.1-1.5 ms long. A thread spawned per batch starts 35-45 µs after the call on this project's
//! VMs (measured at `d66f222`, 2026-11-28): about 0.2 ms of a 6 ms scan. So the workers here
//! live as long as the pool and wait for the next batch: spinning for [`SPIN`] after each job
//! (the gaps inside a scan are shorter), yielding the core to anything else runnable while they
//! do, then sleeping until woken (between scans).
//!
//! The jobs borrow the caller's data for less than `'static`, which no safe channel can carry
//! to a thread that outlives them: [`Pool::run`] erases their lifetime and does not return
//! (nor unwind) before every job has finished, which is what makes that sound, as in
//! `std::thread::scope`.

// The one place the host needs it: a job's lifetime erased while `run` waits (module docs).
#![allow(unsafe_code)]

use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::{JoinHandle, Thread};
use std::time::{Duration, Instant};

use loglio_core::parallel::{Job, MAX_WIDTH, Parallel};

/// How long a worker waits for the next job before it sleeps.
pub const SPIN: Duration = Duration::from_millis(3);

const IDLE: u8 = 0;
const READY: u8 = 1;
const DONE: u8 = 2;
const PANICKED: u8 = 3;
const EXIT: u8 = 4;

/// A job's address with its lifetime erased (see the module docs).
struct JobPtr(*mut (dyn FnMut() + Send + 'static));

// SAFETY: the job itself is `Send`; the pointer only carries it to the worker, and `Pool::run`
// keeps the job alive and untouched until the worker reports it finished.
unsafe impl Send for JobPtr {}

struct Slot {
    state: AtomicU8,
    job: Mutex<Option<JobPtr>>,
}

struct Worker {
    slot: Arc<Slot>,
    thread: Thread,
    handle: Option<JoinHandle<()>>,
}

/// Up to `width` jobs at once: the first on the calling thread, the others on the pool's
/// workers (`width - 1` threads, started once).
pub struct Pool {
    width: usize,
    workers: Vec<Worker>,
    /// One batch at a time (the core's stages never nest them).
    busy: Mutex<()>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool").field("width", &self.width).finish()
    }
}

impl Pool {
    /// A pool for `width` jobs at once (1..=[`MAX_WIDTH`]); fewer if threads cannot be started.
    pub fn new(width: usize) -> Self {
        let width = width.clamp(1, MAX_WIDTH);
        let mut workers = Vec::new();
        for k in 1..width {
            let slot = Arc::new(Slot { state: AtomicU8::new(IDLE), job: Mutex::new(None) });
            let s = slot.clone();
            let spawned =
                std::thread::Builder::new().name(format!("loglio-pool-{k}")).spawn(move || work(&s));
            let Ok(handle) = spawned else { break };
            workers.push(Worker { slot, thread: handle.thread().clone(), handle: Some(handle) });
        }
        Self { width: workers.len() + 1, workers, busy: Mutex::new(()) }
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        for w in &self.workers {
            w.slot.state.store(EXIT, Ordering::Release);
            w.thread.unpark();
        }
        for w in &mut self.workers {
            if let Some(h) = w.handle.take() {
                let _ = h.join();
            }
        }
    }
}

fn work(slot: &Slot) {
    let mut last = Instant::now();
    loop {
        match slot.state.load(Ordering::Acquire) {
            READY => {
                let job = slot.job.lock().map(|mut j| j.take()).unwrap_or(None);
                let ok = match job {
                    // SAFETY: `Pool::run` keeps the job alive and unaliased until this
                    // worker stores DONE or PANICKED below.
                    Some(JobPtr(p)) => catch_unwind(AssertUnwindSafe(|| unsafe { (*p)() })).is_ok(),
                    None => true,
                };
                slot.state.store(if ok { DONE } else { PANICKED }, Ordering::Release);
                last = Instant::now();
            }
            EXIT => return,
            _ => {
                if last.elapsed() < SPIN {
                    std::hint::spin_loop();
                    std::thread::yield_now();
                } else {
                    // Woken by `run` (or `drop`); the timeout only guards a lost wake-up.
                    std::thread::park_timeout(Duration::from_millis(50));
                }
            }
        }
    }
}

impl Parallel for Pool {
    fn width(&self) -> usize {
        self.width
    }

    fn run(&self, jobs: &mut [Job<'_>]) {
        let Some((first, rest)) = jobs.split_first_mut() else { return };
        if rest.is_empty() {
            return first();
        }
        let _one = self.busy.lock().unwrap_or_else(|e| e.into_inner());
        // Jobs beyond the workers run here, after the first.
        let (sent, here) = rest.split_at_mut(rest.len().min(self.workers.len()));
        for (w, job) in self.workers.iter().zip(sent.iter_mut()) {
            let p: *mut (dyn FnMut() + Send + '_) = &mut **job;
            // SAFETY: only the lifetime is erased; this call waits below until the worker is
            // done with the job, so it never outlives the borrow (module docs).
            let p: *mut (dyn FnMut() + Send + 'static) = unsafe { std::mem::transmute(p) };
            if let Ok(mut slot) = w.slot.job.lock() {
                *slot = Some(JobPtr(p));
            }
            w.slot.state.store(READY, Ordering::Release);
            w.thread.unpark();
        }
        let mut panic = catch_unwind(AssertUnwindSafe(|| {
            first();
            for j in here.iter_mut() {
                j();
            }
        }))
        .err();
        let mut worker_panicked = false;
        for w in &self.workers[..sent.len()] {
            let mut spins = 0u32;
            loop {
                match w.slot.state.load(Ordering::Acquire) {
                    DONE => break,
                    PANICKED => {
                        worker_panicked = true;
                        break;
                    }
                    _ => {
                        spins = spins.saturating_add(1);
                        if spins < 1 << 12 {
                            std::hint::spin_loop();
                        } else {
                            std::thread::yield_now();
                        }
                    }
                }
            }
            w.slot.state.store(IDLE, Ordering::Release);
        }
        if let Some(p) = panic.take() {
            resume_unwind(p);
        }
        if worker_panicked {
            panic!("a job of the thread pool panicked");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_job_runs_once_with_any_width_and_count() {
        for width in 1..=4 {
            let pool = Pool::new(width);
            assert_eq!(pool.width(), width);
            for n in 0..=6 {
                for _round in 0..50 {
                    let mut hits = vec![0u32; n];
                    {
                        let mut closures: Vec<_> = hits.iter_mut().map(|h| move || *h += 1).collect();
                        let mut jobs: Vec<Job<'_>> =
                            closures.iter_mut().map(|c| c as &mut (dyn FnMut() + Send)).collect();
                        pool.run(&mut jobs);
                    }
                    assert_eq!(hits, vec![1; n], "width {width} jobs {n}");
                }
            }
        }
    }

    #[test]
    fn workers_wake_after_sleeping() {
        let pool = Pool::new(2);
        for _ in 0..3 {
            std::thread::sleep(SPIN + Duration::from_millis(5));
            let (mut a, mut b) = (0, 0);
            let mut ja = || a += 1;
            let mut jb = || b += 2;
            pool.run(&mut [&mut ja, &mut jb]);
            assert_eq!((a, b), (1, 2));
        }
    }

    #[test]
    fn a_panicking_job_reaches_the_caller_after_the_others_finish() {
        let pool = Pool::new(2);
        let mut done = false;
        let r = catch_unwind(AssertUnwindSafe(|| {
            let mut ja = || panic!("job");
            let mut jb = || {
                std::thread::sleep(Duration::from_millis(20));
                done = true;
            };
            pool.run(&mut [&mut ja, &mut jb]);
        }));
        assert!(r.is_err());
        assert!(done, "the other job finished before the panic went on");
        // The pool still works.
        let mut x = 0;
        let mut jx = || x += 1;
        let mut jy = || {};
        pool.run(&mut [&mut jx, &mut jy]);
        assert_eq!(x, 1);
    }
}
