//! The one-cycle learning-rate schedule of the official SuperFlow code (PyTorch's
//! `OneCycleLR` with cosine annealing, two phases): from `max_lr / div_factor` up to
//! `max_lr` over the first `pct_start` of the steps, then down to
//! `max_lr / div_factor / final_div_factor`. burn 0.22 has no one-cycle scheduler; this
//! is the curve, step by step, for the optimizer to use.

use superflow_common::InvalidSetting;

/// One-cycle parameters (defaults = the official config: lr 0.01, warm-up 20 %, div 25,
/// final div 100).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneCycle {
    /// Peak learning rate.
    pub max_lr: f64,
    /// Steps of the whole run.
    pub total_steps: u64,
    /// Fraction of the steps spent warming up.
    pub pct_start: f64,
    /// Initial lr = `max_lr / div_factor`.
    pub div_factor: f64,
    /// Final lr = initial lr / `final_div_factor`.
    pub final_div_factor: f64,
}

impl OneCycle {
    /// The official recipe over `total_steps`.
    pub fn superflow(total_steps: u64) -> Self {
        Self {
            max_lr: 0.01,
            total_steps,
            pct_start: 0.2,
            div_factor: 25.0,
            final_div_factor: 100.0,
        }
    }

    /// Checks the parameters (PyTorch's rules: at least 2 steps, pct in (0, 1), positive
    /// rates and factors). Errors name the settings of trainer.toml's `[optim]`, which
    /// [`OptimConfig::schedule`](crate::config::OptimConfig::schedule) builds this from.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        if self.total_steps < 2 {
            return Err(InvalidSetting::new(
                "optim.steps",
                self.total_steps,
                "must be at least 2 (one-cycle schedule)",
            ));
        }
        if !(self.pct_start > 0.0 && self.pct_start < 1.0) {
            return Err(InvalidSetting::new(
                "optim.pct_start",
                self.pct_start,
                "must be in (0, 1)",
            ));
        }
        for (setting, value) in [
            ("optim.lr", self.max_lr),
            ("optim.div_factor", self.div_factor),
            ("optim.final_div_factor", self.final_div_factor),
        ] {
            if value.is_nan() || value <= 0.0 {
                return Err(InvalidSetting::new(setting, value, "must be positive"));
            }
        }
        Ok(())
    }

    /// The learning rate at `step` (0-based; steps past the end keep the final rate).
    pub fn lr(&self, step: u64) -> f64 {
        let initial = self.max_lr / self.div_factor;
        let last = initial / self.final_div_factor;
        let cos = |start: f64, end: f64, pct: f64| {
            end + (start - end) / 2.0 * (1.0 + (std::f64::consts::PI * pct).cos())
        };
        // Phase boundaries as PyTorch computes them (floats).
        let warm_end = self.pct_start * self.total_steps as f64 - 1.0;
        let end = self.total_steps as f64 - 1.0;
        let s = (step as f64).min(end);
        if s <= warm_end {
            let pct = if warm_end > 0.0 { s / warm_end } else { 1.0 };
            cos(initial, self.max_lr, pct)
        } else {
            cos(self.max_lr, last, (s - warm_end) / (end - warm_end))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_curve_has_the_official_shape() {
        let s = OneCycle::superflow(1000);
        s.validate().unwrap();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs().max(1e-12);
        // Start, peak at 20 % (step 199 = 0.2 * 1000 - 1), end.
        assert!(close(s.lr(0), 0.01 / 25.0));
        assert!(close(s.lr(199), 0.01));
        assert!(close(s.lr(999), 0.01 / 25.0 / 100.0));
        assert!(close(s.lr(5000), 0.01 / 25.0 / 100.0));
        // Halfway up and halfway down are the means of their phase's ends (cosine).
        let up_mid = 199.0 / 2.0;
        assert!(close(
            OneCycle {
                total_steps: 1000,
                ..s
            }
            .lr(up_mid as u64),
            0.0004 + (0.01 - 0.0004) / 2.0 * (1.0 - (std::f64::consts::PI * (99.0 / 199.0)).cos())
        ));
        assert!(close(s.lr(599), 0.01 / 2.0 + 4e-6 / 2.0));
        // Monotone up, then monotone down.
        let lrs: Vec<f64> = (0..1000).map(|k| s.lr(k)).collect();
        assert!(lrs[..200].windows(2).all(|w| w[0] < w[1]));
        assert!(lrs[199..].windows(2).all(|w| w[0] > w[1]));
        assert!(OneCycle::superflow(1).validate().is_err());
    }
}
