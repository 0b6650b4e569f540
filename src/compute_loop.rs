//! A fixed amount of floating-point work that touches no memory: how far this machine's
//! cores scale from one thread to several when nothing but the cores themselves is
//! shared. `raybatch bench` times it at each thread count in the same rounds as the
//! tracers, so that its figure and theirs come from the same spells of the machine.
//!
//! On a virtual machine two "cores" may be two threads of one physical core, or share it
//! with other guests for a while; a tracer cannot scale further than this loop does then.
//! On BENCHMARKS.md's AVX2-only host, a loop like it read anywhere from 0.76x to 1.70x
//! on two threads over one within a minute (DEVELOPERS.md, "How the bench measures").

use rayon::prelude::*;

/// Chains of multiply-adds kept side by side, eight floats each: enough independent
/// work for every floating-point unit of a core (a chain's step waits on its last one).
const CHAINS: usize = 12;

/// Steps of every chain in one task: about a quarter of a millisecond on one core.
const STEPS: usize = 1 << 17;

/// Each step takes `x` to `x · RATE + (1 − RATE)`, towards 1 without reaching it in
/// [`STEPS`] steps (`RATE^STEPS` ≈ 0.88): no overflow, no subnormals, and a result that
/// depends on every step. Both constants are exact in float32.
const RATE: f32 = 1.0 - 1.0 / (1 << 20) as f32;
const STEP: f32 = 1.0 / (1 << 20) as f32;

/// Tasks in one pass: as many as a full-HD trace pass has, so that threads share them
/// alike.
pub const TASKS: usize = 64;

/// Runs [`TASKS`] tasks on the current rayon pool; returns their sum (so that the work
/// is not left out by the compiler). Every call does the same work and returns the same
/// sum.
pub fn pass() -> f32 {
    (0..TASKS).into_par_iter().map(task).sum()
}

/// One task: the chains started from `seed`, stepped [`STEPS`] times, summed.
fn task(seed: usize) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        return unsafe { task_avx2(seed) };
    }
    chains(seed)
}

/// [`task`] compiled for AVX2, as the tracers' kernels are where the CPU has it: each
/// chain's eight floats take one instruction a step.
///
/// # Safety
///
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn task_avx2(seed: usize) -> f32 {
    chains(seed)
}

#[inline(always)]
fn chains(seed: usize) -> f32 {
    let mut x = [[0f32; 8]; CHAINS];
    for (c, chain) in x.iter_mut().enumerate() {
        for (lane, value) in chain.iter_mut().enumerate() {
            *value = ((seed * CHAINS + c) * 8 + lane) as f32 * 1e-6;
        }
    }
    for _ in 0..STEPS {
        for chain in &mut x {
            for value in chain.iter_mut() {
                *value = *value * RATE + STEP;
            }
        }
    }
    x.iter().flatten().sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chains end where the recurrence says, whichever way the task is compiled:
    /// after `n` steps, `x_n = 1 − (1 − x_0) · RATE^n`, in float64. Float32's rounding
    /// moves each step's increment (about a hundred units in the last place) by at most
    /// half a unit, so the sum stays within 1%; half the steps would end about half as far.
    #[test]
    fn a_task_steps_every_chain_through_the_recurrence() {
        let decay = f64::from(RATE).powi(STEPS as i32);
        for seed in [0, 1, TASKS - 1] {
            let expected: f64 = (0..CHAINS * 8)
                .map(|i| {
                    let x0 = f64::from((seed * CHAINS * 8 + i) as f32 * 1e-6);
                    1.0 - (1.0 - x0) * decay
                })
                .sum();
            for (how, sum) in [("task", task(seed)), ("plain", chains(seed))] {
                let error = (f64::from(sum) - expected).abs();
                assert!(
                    error < 1e-2 * expected,
                    "{how} {seed}: {sum} against {expected}"
                );
            }
        }
    }
}
