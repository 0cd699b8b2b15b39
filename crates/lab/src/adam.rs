//! Adam for training on the CPU: burn's Adam update, every parameter in one
//! pass over host memory.
//!
//! burn's [`burn::optim::Adam`] updates a parameter with a dozen tensor ops
//! (each moment scaled, added, the square root, the bias corrections, the
//! division, the learning rate), each a pass over the parameter that
//! allocates its result. On the CPU the classifier's input projection
//! (7.4 M weights in the lite network) made that 10% of a training step.
//! [`FusedAdam`] does the same arithmetic, in the same order and in f32, in
//! one loop over the parameter, its gradient and its two moments, writing
//! the parameter and the moments in place: the same update to the last bit
//! (checked against burn's in the tests below).
//!
//! In: the parameter, its gradient and the moments of the previous step
//! (burn's [`AdamState`], so a saved optimizer state reads the same). Out:
//! the updated parameter and moments. Off the CPU backend (CUDA, wgpu) it
//! hands the step to burn's Adam on the device.

use burn::optim::decay::WeightDecayConfig;
use burn::optim::{
    Adam, AdamConfig, AdamState, AdaptiveMomentumState, LearningRate, ModuleOptimizer, Optimizer,
};
use burn::prelude::*;

use fall_guard_runtime::model::cpu_device;

/// Adam (β₁ 0.9, β₂ 0.999, ε 1e-5, burn's defaults; no AMSGrad) with an
/// optional L2 weight decay added to the gradient, as burn's
/// `AdamConfig::new().with_weight_decay(..)`.
#[derive(Clone)]
pub struct FusedAdam {
    beta_1: f32,
    beta_2: f32,
    epsilon: f32,
    weight_decay: Option<f32>,
    /// The same optimizer as burn's tensor ops, for devices other than the CPU.
    on_device: Adam,
}

impl FusedAdam {
    /// Adam with burn's default hyper-parameters and `weight_decay` (the
    /// L2 penalty), if any.
    pub fn new(weight_decay: Option<f32>) -> FusedAdam {
        let reference =
            AdamConfig::new().with_weight_decay(weight_decay.map(WeightDecayConfig::new));
        FusedAdam {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-5,
            weight_decay,
            on_device: reference.build(),
        }
    }

    /// The optimizer of a whole module.
    pub fn init(self) -> ModuleOptimizer {
        ModuleOptimizer::from(self)
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let device = tensor.device();
        if device != cpu_device() {
            return self.on_device.step(lr, tensor, grad, state);
        }
        let shape = tensor.shape();
        let mut param = tensor.into_data();
        let grad = grad.into_data();
        let (time, moments) = match state {
            Some(s) => (
                s.momentum.time + 1,
                Some((
                    s.momentum.moment_1.into_data(),
                    s.momentum.moment_2.into_data(),
                )),
            ),
            None => (1, None),
        };
        let (mut moment_1, mut moment_2) = match moments {
            Some(m) => m,
            None => {
                let zeros = || TensorData::new(vec![0.0f32; shape.num_elements()], shape.clone());
                (zeros(), zeros())
            }
        };
        self.update(
            lr,
            time,
            param.as_mut_slice::<f32>().expect("f32 parameter"),
            grad.as_slice::<f32>().expect("f32 gradient"),
            moment_1.as_mut_slice::<f32>().expect("f32 first moment"),
            moment_2.as_mut_slice::<f32>().expect("f32 second moment"),
        );
        let tensor = |data: TensorData| Tensor::<D>::from_data(data, &device);
        let momentum = AdaptiveMomentumState::new(time, tensor(moment_1), tensor(moment_2));
        (tensor(param), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        <Adam as Optimizer>::to_device(state, device)
    }
}

impl FusedAdam {
    /// Step `time` (1 at the first) of one parameter, in place. Each line is
    /// one of burn's tensor ops, in its order (`AdaptiveMomentum::transform`,
    /// `WeightDecay::transform`, `Adam::step`); at the first step the moments
    /// are zero, where burn starts them from the gradient alone: the same
    /// values (`0·β + x` is `x`).
    fn update(
        &self,
        lr: LearningRate,
        time: usize,
        param: &mut [f32],
        grad: &[f32],
        moment_1: &mut [f32],
        moment_2: &mut [f32],
    ) {
        let (b1, b2) = (self.beta_1, self.beta_2);
        let (f1, f2) = (1.0 - b1, 1.0 - b2);
        let t = time as i32;
        let bias_correction2_sqrt = (1.0 - b2.powi(t)).sqrt();
        let combined_factor = bias_correction2_sqrt / (1.0 - b1.powi(t));
        let epsilon = self.epsilon * bias_correction2_sqrt;
        let lr = lr as f32;
        let first = time == 1;
        let n = param.len();
        assert!(grad.len() == n && moment_1.len() == n && moment_2.len() == n);
        for i in 0..n {
            let p = param[i];
            let g = match self.weight_decay {
                Some(penalty) => p * penalty + grad[i],
                None => grad[i],
            };
            let (m1, m2) = if first {
                (g * f1, (g * g) * f2)
            } else {
                (moment_1[i] * b1 + g * f1, moment_2[i] * b2 + (g * g) * f2)
            };
            moment_1[i] = m1;
            moment_2[i] = m2;
            let update = (m1 * combined_factor) / (m2.sqrt() + epsilon);
            param[i] = p - update * lr;
        }
    }
}

#[cfg(test)]
mod tests {
    use burn::nn::{Linear, LinearConfig};
    use burn::optim::GradientsParams;

    use super::*;

    fn values(linear: &Linear) -> Vec<f32> {
        let mut v: Vec<f32> = linear.weight.val().into_data().try_to_vec().unwrap();
        v.extend(
            linear
                .bias
                .as_ref()
                .unwrap()
                .val()
                .into_data()
                .try_to_vec::<f32>()
                .unwrap(),
        );
        v
    }

    /// Several steps of the fused optimizer and of burn's Adam from the same
    /// weights on the same inputs give the same weights, with and without
    /// weight decay, and the state saved by one resumes in the other.
    #[test]
    fn matches_burns_adam_step_by_step() {
        let device = cpu_device().autodiff();
        for weight_decay in [None, Some(0.01)] {
            let start = LinearConfig::new(7, 5).init(&device);
            let mut ours = start.clone();
            let mut theirs = start;
            let mut fused = FusedAdam::new(weight_decay).init();
            let mut reference = AdamConfig::new()
                .with_weight_decay(weight_decay.map(WeightDecayConfig::new))
                .init();
            for step in 0..6 {
                let x = Tensor::<2>::from_data(
                    TensorData::new(
                        (0..21)
                            .map(|i| ((i * 7 + step * 3) % 11) as f32 / 5.0 - 1.0)
                            .collect(),
                        [3, 7],
                    ),
                    &device,
                );
                let loss = |m: &Linear| m.forward(x.clone()).powi_scalar(2).sum();
                let g = GradientsParams::from_grads(loss(&ours).backward(), &ours);
                ours = fused.step(1e-2, ours, g);
                let g = GradientsParams::from_grads(loss(&theirs).backward(), &theirs);
                theirs = reference.step(1e-2, theirs, g);
                assert_eq!(
                    values(&ours),
                    values(&theirs),
                    "step {step}, weight decay {weight_decay:?}"
                );
            }
            // The state is burn's: it resumes burn's optimizer.
            let mut resumed = AdamConfig::new()
                .with_weight_decay(weight_decay.map(WeightDecayConfig::new))
                .init()
                .load_record(fused.to_record());
            let x = Tensor::<2>::ones([2, 7], &device);
            let g = GradientsParams::from_grads(ours.forward(x.clone()).sum().backward(), &ours);
            let a = resumed.step(1e-2, ours.clone(), g);
            let g = GradientsParams::from_grads(theirs.forward(x).sum().backward(), &theirs);
            let b = reference.step(1e-2, theirs.clone(), g);
            assert_eq!(values(&a), values(&b));
        }
    }
}
