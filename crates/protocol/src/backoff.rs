//! Retrying a peer that cannot be reached: the delays between attempts,
//! shared by workers finding their scheduler and clients attaching to
//! their job again.

use std::time::Duration;

/// Delays doubling from 100 ms to 5 s, each shortened by up to half at
/// random, so that a farm's workers and clients do not all knock at once
/// when a scheduler comes back.
#[derive(Debug, Default)]
pub struct Backoff {
    failures: u32,
}

impl Backoff {
    const FIRST: Duration = Duration::from_millis(100);
    const MAX: Duration = Duration::from_secs(5);

    /// The delay before the next attempt.
    pub fn next_delay(&mut self) -> Duration {
        let d = Self::FIRST
            .saturating_mul(1 << self.failures.min(16))
            .min(Self::MAX);
        self.failures += 1;
        let mut b = [0u8; 1];
        let jitter = match getrandom::fill(&mut b) {
            Ok(()) => b[0] as f64 / 510.0,
            Err(_) => 0.0,
        };
        d.mul_f64(1.0 - jitter)
    }

    /// After a success: start again from the shortest delay.
    pub fn reset(&mut self) {
        self.failures = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::Backoff;
    use std::time::Duration;

    #[test]
    fn delays_double_up_to_the_cap_and_reset() {
        let mut b = Backoff::default();
        let d: Vec<Duration> = (0..10).map(|_| b.next_delay()).collect();
        assert!(d[0] >= Duration::from_millis(50) && d[0] <= Duration::from_millis(100));
        assert!(d[3] >= Duration::from_millis(400) && d[3] <= Duration::from_millis(800));
        assert!(d[9] >= Duration::from_millis(2500) && d[9] <= Duration::from_secs(5));
        b.reset();
        assert!(b.next_delay() <= Duration::from_millis(100));
    }
}
