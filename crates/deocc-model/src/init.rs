//! Seeded parameter initialisation and noise. candle's CPU device cannot be seeded, so every
//! random number of training and sampling comes from ChaCha8 generators seeded from the config.

use std::sync::Mutex;

use candle_core::{DType, Device, Result, Shape, Tensor, Var};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// Gaussian noise of `shape` from `rng`.
pub fn randn(shape: impl Into<Shape>, rng: &mut impl Rng, device: &Device) -> Result<Tensor> {
    let shape = shape.into();
    let data: Vec<f32> = (0..shape.elem_count())
        .map(|_| StandardNormal.sample(rng))
        .collect();
    Tensor::from_vec(data, shape, device)
}

/// A VarBuilder backend that creates variables in a [`VarMap`] with values drawn from a seeded
/// generator, in the order the model asks for them (deterministic for a given model code).
pub struct SeededInit {
    varmap: VarMap,
    rng: Mutex<ChaCha8Rng>,
}

impl SeededInit {
    pub fn new(varmap: VarMap, seed: u64) -> Self {
        Self {
            varmap,
            rng: Mutex::new(ChaCha8Rng::seed_from_u64(seed)),
        }
    }
}

impl SimpleBackend for SeededInit {
    fn get(&self, s: Shape, name: &str, h: Init, dtype: DType, dev: &Device) -> Result<Tensor> {
        let data = self.varmap.data();
        let mut vars = data
            .lock()
            .map_err(|_| candle_core::Error::msg("var map lock poisoned"))?;
        if let Some(v) = vars.get(name) {
            if v.shape() != &s {
                candle_core::bail!(
                    "variable {name} exists with shape {:?}, asked for {s:?}",
                    v.shape()
                );
            }
            return Ok(v.as_tensor().clone());
        }
        let mut rng = self
            .rng
            .lock()
            .map_err(|_| candle_core::Error::msg("rng lock poisoned"))?;
        let n = s.elem_count();
        let values: Vec<f32> = match h {
            Init::Const(c) => vec![c as f32; n],
            Init::Randn { mean, stdev } => (0..n)
                .map(|_| {
                    let z: f32 = StandardNormal.sample(&mut *rng);
                    mean as f32 + stdev as f32 * z
                })
                .collect(),
            Init::Uniform { lo, up } => (0..n)
                .map(|_| rng.random_range(lo as f32..up as f32))
                .collect(),
            other => candle_core::bail!(
                "initialisation {other:?} of {name} is not supported by the seeded initialiser"
            ),
        };
        let t = Tensor::from_vec(values, s, dev)?.to_dtype(dtype)?;
        let var = Var::from_tensor(&t)?;
        vars.insert(name.to_string(), var.clone());
        Ok(var.as_tensor().clone())
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> Result<Tensor> {
        candle_core::bail!("variable {name} must be created with a shape and an initialisation")
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.varmap
            .data()
            .lock()
            .map(|d| d.contains_key(name))
            .unwrap_or(false)
    }
}
