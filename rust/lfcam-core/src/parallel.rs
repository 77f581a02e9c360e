//! The one place that decides threading: lfcam's own rayon pool and the chunking
//! policy every kernel uses.
//!
//! # The pool
//! Kernels never touch rayon's global pool. They run in a process-wide [`ThreadPool`]
//! built lazily on first use, with [`ENV_NUM_THREADS`] (`LFCAM_NUM_THREADS`, read once,
//! when the pool is first needed) threads if that is set to a positive integer, else
//! one per available core. [`set_num_threads`] replaces it.
//!
//! # The calling thread takes part
//! On Linux, calls from the process's main thread (where Python runs) use a second
//! pool of the same size in which that thread is worker 0 ([`ThreadPoolBuilder::
//! use_current_thread`]): it works on its own job instead of handing it over and
//! sleeping until the job is done, as OpenMP's and OpenCV's calling threads do. A
//! hand-over makes the scheduler wake every worker at once on whichever cores look
//! idle, and the caller's own core idles: a short kernel called right after
//! single-threaded work ran as if on one thread (measured: docs/tuning.md, "Threads
//! and build"). The main thread joins one such
//! pool for good (rayon cannot take it out again), so it is built only for 2 threads
//! or more; if the thread count changes afterwards, the main thread's calls use the
//! ordinary pool of the new size, and the first one again when the count returns to
//! it. Other threads always use the ordinary pool, whose callers block while its
//! workers run the job. (Rust tests run on spawned threads: this path is tested from
//! Python, `tests/test_threads.py`.)
//!
//! # Fork safety
//! After `fork()` (Python's `multiprocessing` with the `fork` start method) the child
//! has a copy of the pool's bookkeeping but none of its threads: a job sent to it would
//! wait forever. The pool therefore remembers the id of the process that built it, and
//! [`install`] in another process builds a fresh pool for that process. The stale pool
//! is leaked ([`std::mem::forget`]), never dropped: dropping it would talk to threads
//! that do not exist in the child. A child forked from the main thread inherits its
//! membership of the parent's home pool (copied, threads gone); its calls run in the
//! child's pool from a scoped helper thread, so that they never wait on that copy's
//! locks, one of which a parent worker may have held at the fork. (The only remaining
//! hazard is a fork taken while another thread holds this module's lock, which is
//! held for microseconds.)
//!
//! # Chunking
//! [`for_each_row_chunk`] splits an output made of equal-length rows into tasks of
//! whole rows: serial on the calling thread below [`SERIAL_BELOW_BYTES`] or with one
//! thread, else in the pool, with tasks of about [`TASK_BYTES`] and at least
//! [`TASKS_PER_THREAD`] tasks per thread. One loop body serves both paths. Work that
//! is not rows of one output comes in tasks the kernel makes itself (one per view, per
//! band of a fine grid, per range of triangles), which [`map_tasks`] and
//! [`for_each_task_init`] run under the same serial-or-pool rule. Kernels use these
//! functions and never rayon directly.

use std::sync::{Arc, Mutex, MutexGuard};

use rayon::prelude::*;
use rayon::{ThreadPool, ThreadPoolBuilder};

use crate::error::{Error, Result};

/// Environment variable holding the default number of threads.
pub const ENV_NUM_THREADS: &str = "LFCAM_NUM_THREADS";

/// Upper bound accepted by [`set_num_threads`] and [`ENV_NUM_THREADS`].
pub const MAX_THREADS: usize = 1024;

/// Work whose output is smaller than this many bytes runs serially: there, a copy takes
/// on the order of 10 us, comparable to waking the pool's threads and joining them. A
/// starting value, to be tuned per kernel with its criterion bench.
pub const SERIAL_BELOW_BYTES: usize = 256 * 1024;

/// Target output bytes per parallel task: large enough to amortise task overhead,
/// small enough (a fraction of L2) to balance load.
pub const TASK_BYTES: usize = 64 * 1024;

/// Minimum number of tasks per thread, so one slow thread does not hold everyone up.
pub const TASKS_PER_THREAD: usize = 4;

struct Pool {
    pool: Arc<ThreadPool>,
    pid: u32,
}

struct State {
    /// The thread count the next pool will have; `None` until first resolved.
    num_threads: Option<usize>,
    pool: Option<Pool>,
    /// The pool the main thread is worker 0 of, and its size (built on the main
    /// thread's first call; never replaced).
    home: Option<(Pool, usize)>,
}

static STATE: Mutex<State> = Mutex::new(State {
    num_threads: None,
    pool: None,
    home: None,
});

fn lock() -> MutexGuard<'static, State> {
    // The lock is never held across user code, so poisoning cannot leave the state
    // half-updated; recover instead of panicking.
    STATE
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// The default thread count: `LFCAM_NUM_THREADS` if it is an integer in
/// `1..=MAX_THREADS`, else the available parallelism (1 if unknown).
fn default_num_threads() -> usize {
    std::env::var(ENV_NUM_THREADS)
        .ok()
        .and_then(|v| v.trim().parse::<usize>().ok())
        .filter(|n| (1..=MAX_THREADS).contains(n))
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

fn check_num_threads(n: usize) -> Result<()> {
    if (1..=MAX_THREADS).contains(&n) {
        Ok(())
    } else {
        Err(Error::invalid_argument(
            "n",
            format!("number of threads must be between 1 and {MAX_THREADS}, got {n}"),
        ))
    }
}

fn build_pool(n: usize) -> Result<Pool> {
    let pool = ThreadPoolBuilder::new()
        .num_threads(n)
        .thread_name(|i| format!("lfcam-{i}"))
        .build()
        .map_err(|e| {
            Error::invalid_argument("n", format!("could not start {n} worker threads: {e}"))
        })?;
    Ok(Pool {
        pool: Arc::new(pool),
        pid: std::process::id(),
    })
}

/// Disposes of a pool that is being replaced: dropped if it belongs to this process,
/// leaked if it was inherited through `fork()` (its threads do not exist here).
fn retire(old: Option<Pool>) {
    if let Some(old) = old
        && old.pid != std::process::id()
    {
        std::mem::forget(old);
    }
}

/// The pool for this process, built now if there is none or if the existing one was
/// built in the parent of a fork.
fn current_pool() -> Result<Arc<ThreadPool>> {
    let mut state = lock();
    let pid = std::process::id();
    if let Some(p) = state.pool.as_ref().filter(|p| p.pid == pid) {
        return Ok(Arc::clone(&p.pool));
    }
    let n = *state.num_threads.get_or_insert_with(default_num_threads);
    let fresh = build_pool(n)?;
    let pool = Arc::clone(&fresh.pool);
    retire(state.pool.replace(fresh));
    Ok(pool)
}

/// Number of threads kernels run on: the current pool's, or the one the pool will
/// have when it is built.
pub fn num_threads() -> usize {
    let mut state = lock();
    *state.num_threads.get_or_insert_with(default_num_threads)
}

/// Replaces the pool by one with `n` threads (built now, so failure is reported here).
/// Work already running in the old pool finishes there.
///
/// # Errors
/// [`Error::InvalidArgument`] (argument `"n"`) if `n` is 0 or above [`MAX_THREADS`], or
/// if the operating system refuses to start the threads.
pub fn set_num_threads(n: usize) -> Result<()> {
    check_num_threads(n)?;
    let fresh = build_pool(n)?;
    let mut state = lock();
    state.num_threads = Some(n);
    retire(state.pool.replace(fresh));
    Ok(())
}

/// Runs `f` inside lfcam's pool (building it if needed, and rebuilding it in a forked
/// child), so that rayon parallel iterators in `f` use that pool. Called from a worker
/// of the pool, it runs `f` directly; called from the main thread, it runs `f` there,
/// in the pool that thread takes part in (see the module notes).
///
/// # Errors
/// [`Error::InvalidArgument`] (argument `"n"`) if the pool has to be built and the
/// operating system refuses to start its threads.
pub fn install<R, F>(f: F) -> Result<R>
where
    F: FnOnce() -> R + Send,
    R: Send,
{
    match home_pool() {
        // The calling thread is one of this pool's workers: `f` runs right here.
        Home::Member(home) => return Ok(home.install(f)),
        Home::Inherited => {
            // A forked child's main thread, still registered in its copy of the
            // parent's pool, whose threads do not exist here: waiting there would touch
            // that copy's locks (one may have been copied locked). The call goes to
            // this process's pool from a fresh thread instead.
            let pool = current_pool()?;
            return std::thread::scope(|s| s.spawn(|| pool.install(f)).join())
                .map_err(|panic| std::panic::resume_unwind(panic));
        }
        Home::No => {}
    }
    let pool = current_pool()?;
    Ok(pool.install(f))
}

/// What [`home_pool`] found.
enum Home {
    /// The calling thread is a worker of the pool the main thread takes part in, which
    /// has the current thread count.
    Member(Arc<ThreadPool>),
    /// The calling thread is a worker of a pool inherited through `fork()`.
    Inherited,
    /// Neither: the ordinary pool.
    No,
}

/// The pool the calling thread takes part in, if it is the process's main thread, the
/// thread count is at least 2 and that pool has it (built now if the main thread is in
/// no pool yet; if it cannot be built, the ordinary pool serves).
fn home_pool() -> Home {
    let mut state = lock();
    let n = *state.num_threads.get_or_insert_with(default_num_threads);
    let pid = std::process::id();
    if let Some((home, size)) = state.home.as_ref().filter(|(h, _)| h.pid == pid) {
        // Also true in the pool's other workers (a nested call runs inline there).
        let member = home.pool.current_thread_index().is_some();
        return if member && *size == n {
            Home::Member(Arc::clone(&home.pool))
        } else {
            Home::No
        };
    }
    // A home pool here is one inherited through `fork()`.
    if let Some((inherited, _)) = &state.home
        && inherited.pool.current_thread_index().is_some()
    {
        return Home::Inherited;
    }
    // A worker of an ordinary pool (a nested call): it stays in its pool.
    if rayon::current_thread_index().is_some() {
        return Home::No;
    }
    // One thread: the ordinary pool, so that the main thread is still free to take
    // part in a pool of the default size later (it can join only one).
    if n < 2 || !is_main_thread() {
        return Home::No;
    }
    let Ok(pool) = ThreadPoolBuilder::new()
        .num_threads(n)
        .thread_name(|i| format!("lfcam-{i}"))
        .use_current_thread()
        .build()
    else {
        return Home::No;
    };
    let home = Pool {
        pool: Arc::new(pool),
        pid,
    };
    let pool = Arc::clone(&home.pool);
    // One inherited through `fork()` (by a thread that was not the parent's main
    // thread) is leaked, not dropped: see [`retire`].
    if let Some((old, _)) = state.home.replace((home, n)) {
        retire(Some(old));
    }
    Home::Member(pool)
}

/// Whether the calling thread is the process's main thread (on Linux: its thread id
/// is the process id, read from `/proc/thread-self`; elsewhere: never, so every call
/// uses the ordinary pool).
fn is_main_thread() -> bool {
    thread_local! {
        static MAIN: bool = std::fs::read_link("/proc/thread-self").is_ok_and(|link| {
            // "<pid>/task/<tid>"
            link.file_name()
                .and_then(|tid| tid.to_str())
                .is_some_and(|tid| tid == std::process::id().to_string())
        });
    }
    MAIN.with(|m| *m)
}

/// Rows per task for `n_rows` rows of `row_bytes` bytes on `threads` threads: about
/// [`TASK_BYTES`] per task, but at least [`TASKS_PER_THREAD`] tasks per thread when
/// there are enough rows; never 0.
pub fn rows_per_task(n_rows: usize, row_bytes: usize, threads: usize) -> usize {
    let by_size = TASK_BYTES.div_ceil(row_bytes.max(1));
    let by_balance = n_rows.div_ceil(threads.max(1).saturating_mul(TASKS_PER_THREAD));
    by_size.min(by_balance).max(1)
}

/// Whether an output of `total_bytes` bytes should be produced serially.
pub fn run_serially(total_bytes: usize, threads: usize) -> bool {
    threads <= 1 || total_bytes < SERIAL_BELOW_BYTES
}

/// Calls `body(first_row, rows)` over `out`, viewed as rows of `row_len` elements, in
/// tasks of whole rows (`rows.len()` is a multiple of `row_len`; `first_row` is the
/// index of its first row in `out`). Small outputs run serially on the calling thread,
/// others in lfcam's pool (see the module docs). The first error returned by `body`
/// is returned (other tasks may or may not have run).
///
/// # Errors
/// [`Error::InvalidArgument`] (argument `"out"`) if `out.len()` is not a multiple of
/// `row_len`; the pool's errors ([`install`]); `body`'s errors.
pub fn for_each_row_chunk<T, F>(out: &mut [T], row_len: usize, body: F) -> Result<()>
where
    T: Send,
    F: Fn(usize, &mut [T]) -> Result<()> + Sync + Send,
{
    for_each_row_chunk_min(out, row_len, 1, body)
}

/// [`for_each_row_chunk`] with at least `min_rows` rows per task (fewer only in the
/// last task): for kernels whose tasks have a setup cost per task, such as a buffer
/// shared by neighbouring rows. The kernel states and justifies its `min_rows`.
///
/// # Errors
/// As [`for_each_row_chunk`].
pub fn for_each_row_chunk_min<T, F>(
    out: &mut [T],
    row_len: usize,
    min_rows: usize,
    body: F,
) -> Result<()>
where
    T: Send,
    F: Fn(usize, &mut [T]) -> Result<()> + Sync + Send,
{
    for_each_row_chunk_init(
        out,
        row_len,
        min_rows,
        || (),
        |(), first, rows| body(first, rows),
    )
}

/// [`for_each_row_chunk_min`] with per-worker state: `body(&mut state, first_row,
/// rows)`, `state` made by `init()` once per run of tasks one thread does in a row
/// (rayon's `try_for_each_init`: a few times per thread, not once per task; once in
/// all when serial). For scratch buffers that tasks would otherwise allocate and clear
/// each time.
///
/// # Errors
/// As [`for_each_row_chunk`].
pub fn for_each_row_chunk_init<T, S, I, F>(
    out: &mut [T],
    row_len: usize,
    min_rows: usize,
    init: I,
    body: F,
) -> Result<()>
where
    T: Send,
    I: Fn() -> S + Sync + Send,
    F: Fn(&mut S, usize, &mut [T]) -> Result<()> + Sync + Send,
{
    if out.is_empty() {
        return Ok(());
    }
    if row_len == 0 || !out.len().is_multiple_of(row_len) {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "has {} elements, not a whole number of rows of {row_len}",
                out.len()
            ),
        ));
    }
    let n_rows = out.len() / row_len;
    let elem = std::mem::size_of::<T>().max(1);
    let total_bytes = out.len().saturating_mul(elem);
    let threads = num_threads();
    let rows = rows_per_task(n_rows, row_len.saturating_mul(elem), threads)
        .max(min_rows)
        .min(n_rows);
    // `1 <= rows <= n_rows`, so `rows * row_len <= out.len()`: no overflow, never 0.
    let chunk = rows * row_len;
    let task = |state: &mut S, (i, rows_out): (usize, &mut [T])| body(state, i * rows, rows_out);
    if run_serially(total_bytes, threads) {
        let mut state = init();
        out.chunks_mut(chunk)
            .enumerate()
            .try_for_each(|item| task(&mut state, item))
    } else {
        install(|| {
            out.par_chunks_mut(chunk)
                .enumerate()
                .try_for_each_init(&init, task)
        })?
    }
}

/// Like [`for_each_row_chunk`] for two outputs with the same number of rows (of
/// `row_len_a` and `row_len_b` elements): `body(first_row, rows_a, rows_b)` gets the
/// same rows of both. The chunking policy is the same, counting the bytes of a row of
/// both outputs together.
///
/// # Errors
/// [`Error::InvalidArgument`] (argument `"out"`) if either output is not a whole number
/// of rows or if they have different numbers of rows; the pool's errors; `body`'s errors.
pub fn for_each_row_chunk_pair<A, B, F>(
    out_a: &mut [A],
    out_b: &mut [B],
    row_len_a: usize,
    row_len_b: usize,
    body: F,
) -> Result<()>
where
    A: Send,
    B: Send,
    F: Fn(usize, &mut [A], &mut [B]) -> Result<()> + Sync + Send,
{
    let whole = |len: usize, row_len: usize| {
        (row_len > 0 && len.is_multiple_of(row_len)).then(|| len / row_len)
    };
    let n_rows = match (whole(out_a.len(), row_len_a), whole(out_b.len(), row_len_b)) {
        (Some(a), Some(b)) if a == b => a,
        _ => {
            return Err(Error::invalid_argument(
                "out",
                format!(
                    "outputs of {} and {} elements are not the same number of rows of {row_len_a} \
                     and {row_len_b}",
                    out_a.len(),
                    out_b.len()
                ),
            ));
        }
    };
    if n_rows == 0 {
        return Ok(());
    }
    let row_bytes = row_len_a
        .saturating_mul(std::mem::size_of::<A>())
        .saturating_add(row_len_b.saturating_mul(std::mem::size_of::<B>()))
        .max(1);
    let total_bytes = row_bytes.saturating_mul(n_rows);
    let threads = num_threads();
    let rows = rows_per_task(n_rows, row_bytes, threads);
    let task = |(i, (a, b)): (usize, (&mut [A], &mut [B]))| body(i * rows, a, b);
    let (chunk_a, chunk_b) = (rows * row_len_a, rows * row_len_b);
    if run_serially(total_bytes, threads) {
        out_a
            .chunks_mut(chunk_a)
            .zip(out_b.chunks_mut(chunk_b))
            .enumerate()
            .try_for_each(task)
    } else {
        install(|| {
            out_a
                .par_chunks_mut(chunk_a)
                .zip(out_b.par_chunks_mut(chunk_b))
                .enumerate()
                .try_for_each(task)
        })?
    }
}

/// `f(i)` for every `i` in `0..n`, one task each, collected in order: serially on the
/// calling thread when `work_bytes` (the tasks' output or input, the kernel's measure
/// of the work as for [`run_serially`]) is small, with one thread, or for one task;
/// else in lfcam's pool. For a few coarse tasks whose results are put together
/// afterwards (one per view, one per chunk of samples).
///
/// # Errors
/// The pool's errors ([`install`]); the first error `f` returns (other tasks may or
/// may not have run).
pub fn map_tasks<T, F>(n: usize, work_bytes: usize, f: F) -> Result<Vec<T>>
where
    T: Send,
    F: Fn(usize) -> Result<T> + Sync + Send,
{
    if n <= 1 || run_serially(work_bytes, num_threads()) {
        (0..n).map(f).collect()
    } else {
        install(|| (0..n).into_par_iter().map(f).collect())?
    }
}

/// `body(&mut state, i, item)` for the `i`-th of `items`, tasks the kernel made (each
/// owning its part of the output: a band of rows, a frame buffer), one task per item,
/// under the rule of [`map_tasks`]; `state` as in [`for_each_row_chunk_init`] (made by
/// `init` once per run of tasks one thread does in a row; once in all when serial,
/// where the items run in order).
///
/// # Errors
/// The pool's errors ([`install`]); the first error `body` returns (other tasks may
/// or may not have run).
pub fn for_each_task_init<I, S, N, F>(
    items: Vec<I>,
    work_bytes: usize,
    init: N,
    body: F,
) -> Result<()>
where
    I: Send,
    N: Fn() -> S + Sync + Send,
    F: Fn(&mut S, usize, I) -> Result<()> + Sync + Send,
{
    let task = |state: &mut S, (i, item): (usize, I)| body(state, i, item);
    if items.len() <= 1 || run_serially(work_bytes, num_threads()) {
        let mut state = init();
        items
            .into_iter()
            .enumerate()
            .try_for_each(|item| task(&mut state, item))
    } else {
        install(|| {
            items
                .into_par_iter()
                .enumerate()
                .try_for_each_init(&init, task)
        })?
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_chunks_with_state_cover_every_row_once() {
        for n_rows in [1usize, 7, 300, 5000] {
            for row_len in [1usize, 3, 1000] {
                let mut out = vec![0u32; n_rows * row_len];
                for_each_row_chunk_init(
                    &mut out,
                    row_len,
                    3,
                    Vec::<u32>::new,
                    |seen, first, rows| {
                        assert!(
                            rows.len() >= 3 * row_len || first + rows.len() / row_len == n_rows
                        );
                        for (k, row) in rows.chunks_exact_mut(row_len).enumerate() {
                            seen.push(0);
                            row.fill(u32::try_from(first + k).unwrap() + 1);
                        }
                        Ok(())
                    },
                )
                .unwrap();
                for (r, row) in out.chunks_exact(row_len).enumerate() {
                    assert!(
                        row.iter().all(|&v| v as usize == r + 1),
                        "{n_rows} {row_len}"
                    );
                }
            }
        }
        let mut out = vec![0u8; 10];
        assert!(for_each_row_chunk_init(&mut out, 3, 1, || (), |_, _, _| Ok(())).is_err());
    }

    #[test]
    fn row_chunk_pairs_see_the_same_rows() {
        for n_rows in [0usize, 1, 7, 300, 70_000] {
            let mut a = vec![0u32; n_rows * 3];
            let mut b = vec![0u8; n_rows];
            for_each_row_chunk_pair(&mut a, &mut b, 3, 1, |first, ra, rb| {
                assert_eq!(ra.len(), 3 * rb.len());
                for (k, (row, x)) in ra.chunks_exact_mut(3).zip(rb.iter_mut()).enumerate() {
                    row.fill(u32::try_from(first + k).unwrap());
                    *x = ((first + k) % 251) as u8;
                }
                Ok(())
            })
            .unwrap();
            for r in 0..n_rows {
                assert!(a[3 * r..3 * r + 3].iter().all(|&v| v as usize == r));
                assert_eq!(b[r] as usize, r % 251);
            }
        }
        let (mut a, mut b) = (vec![0u8; 6], vec![0u8; 4]);
        assert!(for_each_row_chunk_pair(&mut a, &mut b, 2, 1, |_, _, _| Ok(())).is_err());
        assert!(for_each_row_chunk_pair(&mut a, &mut b, 0, 1, |_, _, _| Ok(())).is_err());
    }

    #[test]
    fn tasks_run_once_each_in_order_and_propagate_errors() {
        for (n, bytes) in [(0usize, 0usize), (1, 1 << 30), (7, 10), (300, 1 << 30)] {
            let got = map_tasks(n, bytes, |i| Ok(3 * i)).unwrap();
            assert_eq!(got, (0..n).map(|i| 3 * i).collect::<Vec<_>>());
            let mut out = vec![0usize; n];
            let items: Vec<(usize, &mut usize)> = out.iter_mut().enumerate().collect();
            for_each_task_init(
                items,
                bytes,
                || 0usize,
                |seen, i, (k, o)| {
                    assert_eq!(i, k);
                    *seen += 1;
                    *o = i + 1;
                    Ok(())
                },
            )
            .unwrap();
            assert!(out.iter().enumerate().all(|(i, &v)| v == i + 1));
        }
        let err = map_tasks(50, 1 << 30, |i| {
            if i == 20 {
                Err(Error::Numerical("task 20".into()))
            } else {
                Ok(i)
            }
        });
        assert!(matches!(err, Err(Error::Numerical(_))));
        let err = for_each_task_init(
            vec![1, 2, 3],
            1 << 30,
            || (),
            |(), i, _| {
                if i == 1 {
                    Err(Error::Numerical("task 1".into()))
                } else {
                    Ok(())
                }
            },
        );
        assert!(matches!(err, Err(Error::Numerical(_))));
    }

    #[test]
    fn rows_per_task_is_never_zero_and_balances() {
        assert_eq!(rows_per_task(0, 0, 0), 1);
        assert_eq!(rows_per_task(1, 1, 1), 1);
        // Big rows: one row per task.
        assert_eq!(rows_per_task(1000, 1 << 20, 2), 1);
        // Small rows: ~TASK_BYTES per task.
        assert_eq!(rows_per_task(100_000, 1024, 2), 64);
        // Few rows: split for balance instead.
        assert_eq!(rows_per_task(16, 1024, 2), 2);
    }

    #[test]
    fn serial_threshold() {
        assert!(run_serially(SERIAL_BELOW_BYTES - 1, 8));
        assert!(!run_serially(SERIAL_BELOW_BYTES, 8));
        assert!(run_serially(usize::MAX, 1));
    }

    #[test]
    fn check_rejects_zero_and_huge() {
        assert!(check_num_threads(0).is_err());
        assert!(check_num_threads(MAX_THREADS + 1).is_err());
        assert!(check_num_threads(1).is_ok());
        assert!(matches!(
            set_num_threads(0),
            Err(Error::InvalidArgument { ref arg, .. }) if arg == "n"
        ));
    }

    #[test]
    fn install_runs_in_lfcam_pool() {
        let name = install(|| std::thread::current().name().map(str::to_owned)).unwrap();
        assert!(name.unwrap_or_default().starts_with("lfcam-"));
        // Nested install from a worker runs inline.
        let nested = install(|| install(|| rayon::current_thread_index().is_some()).unwrap());
        assert!(nested.unwrap());
    }

    #[test]
    fn row_chunks_cover_every_row_once_serial_and_parallel() {
        for n_rows in [1usize, 7, 300, 5000] {
            for row_len in [1usize, 3, 1000] {
                let mut out = vec![0u32; n_rows * row_len];
                for_each_row_chunk(&mut out, row_len, |first, rows| {
                    for (k, row) in rows.chunks_exact_mut(row_len).enumerate() {
                        row.fill(u32::try_from(first + k).unwrap() + 1);
                    }
                    Ok(())
                })
                .unwrap();
                for (r, row) in out.chunks_exact(row_len).enumerate() {
                    assert!(
                        row.iter().all(|&v| v as usize == r + 1),
                        "{n_rows} {row_len}"
                    );
                }
            }
        }
    }

    #[test]
    fn row_chunks_reject_ragged_output_and_propagate_errors() {
        let mut out = vec![0u8; 10];
        assert!(for_each_row_chunk(&mut out, 3, |_, _| Ok(())).is_err());
        assert!(for_each_row_chunk(&mut out, 0, |_, _| Ok(())).is_err());
        assert!(for_each_row_chunk(&mut [0u8; 0], 0, |_, _| Ok(())).is_ok());
        let mut big = vec![0u8; 4 * SERIAL_BELOW_BYTES];
        let err = for_each_row_chunk(&mut big, 1024, |first, _| {
            if first >= 512 {
                Err(Error::Numerical(format!("row {first}")))
            } else {
                Ok(())
            }
        });
        assert!(matches!(err, Err(Error::Numerical(_))));
    }
}
