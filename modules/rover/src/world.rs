//! The world the simulated devices share: rolling terrain with rocks, seen and sensed from the
//! rover's pose. Every device module builds the same [`Terrain`] from its `terrain` parameter,
//! and reads the rover's pose from the world simulator's output, so what the camera sees, what
//! the range sensor measures and what the encoders count agree.

use nalgebra::{Isometry2, Point2, Vector2};

/// A rock: a vertical cylinder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rock {
    pub center: Point2<f64>,
    pub radius: f64,
    pub height: f64,
}

/// Terrain height field and rocks.
#[derive(Debug, Clone, PartialEq)]
pub struct Terrain {
    pub rocks: Vec<Rock>,
    /// Amplitude of the rolling hills, m.
    pub hills: f64,
}

/// Radius of the rover's footprint, m (for collisions).
pub const ROVER_RADIUS: f64 = 0.35;

impl Terrain {
    /// The terrain named by a module's `terrain` parameter: `"mars-yard"` (the default) or
    /// `"flat"` (no rocks, no hills).
    pub fn named(name: &str) -> Option<Terrain> {
        match name {
            "mars-yard" => Some(Terrain::mars_yard()),
            "flat" => Some(Terrain {
                rocks: Vec::new(),
                hills: 0.0,
            }),
            _ => None,
        }
    }

    /// A test yard: gentle hills and a scatter of rocks, none on the demo's paths.
    pub fn mars_yard() -> Terrain {
        let rock = |x: f64, y: f64, radius: f64, height: f64| Rock {
            center: Point2::new(x, y),
            radius,
            height,
        };
        Terrain {
            rocks: vec![
                rock(9.0, 1.5, 0.6, 0.8),
                rock(5.0, -4.0, 0.5, 0.6),
                rock(-3.0, 4.0, 0.8, 1.0),
                rock(12.0, 8.0, 1.0, 1.2),
                rock(2.0, 9.0, 0.4, 0.5),
                rock(-6.0, -5.0, 0.7, 0.9),
                rock(14.0, -3.0, 0.6, 0.7),
            ],
            hills: 0.3,
        }
    }

    /// Ground height at (x, y), m.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        self.hills * ((0.21 * x).sin() * (0.17 * y).cos() + 0.5 * (0.11 * x + 0.07 * y).sin())
    }

    /// Ground slope (dh/dx, dh/dy) at (x, y).
    pub fn gradient(&self, x: f64, y: f64) -> Vector2<f64> {
        let e = 1e-3;
        Vector2::new(
            (self.height(x + e, y) - self.height(x - e, y)) / (2.0 * e),
            (self.height(x, y + e) - self.height(x, y - e)) / (2.0 * e),
        )
    }

    /// Pitch (nose up positive) and roll (left side up positive) of a rover at `pose`.
    pub fn attitude(&self, pose: &Isometry2<f64>) -> (f64, f64) {
        let p = pose.translation.vector;
        let g = self.gradient(p.x, p.y);
        let heading = pose.rotation * Vector2::x();
        let left = pose.rotation * Vector2::y();
        (g.dot(&heading).atan(), -g.dot(&left).atan())
    }

    /// Whether a rover centred at `p` touches a rock.
    pub fn collides(&self, p: &Point2<f64>) -> bool {
        self.rocks
            .iter()
            .any(|r| (r.center - p).norm() < r.radius + ROVER_RADIUS)
    }

    /// Distance from `origin` along unit `dir` to the first rock, if within `max`.
    pub fn ray(&self, origin: &Point2<f64>, dir: &Vector2<f64>, max: f64) -> Option<(f64, &Rock)> {
        let mut best: Option<(f64, &Rock)> = None;
        for rock in &self.rocks {
            let oc = origin - rock.center;
            let b = oc.dot(dir);
            let c = oc.norm_squared() - rock.radius * rock.radius;
            let disc = b * b - c;
            if disc < 0.0 {
                continue;
            }
            let t = -b - disc.sqrt();
            let t = if t < 0.0 { -b + disc.sqrt() } else { t };
            if t >= 0.0 && t <= max && best.is_none_or(|(d, _)| t < d) {
                best = Some((t, rock));
            }
        }
        best
    }
}

/// A pinhole camera on the rover.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraModel {
    pub width: usize,
    pub height: usize,
    /// Horizontal field of view, rad.
    pub fov: f64,
    /// Height of the lens above ground, m.
    pub mount_height: f64,
    /// Farthest distance drawn, m.
    pub far: f64,
}

impl CameraModel {
    pub const BEETLE: CameraModel = CameraModel {
        width: 320,
        height: 240,
        fov: 70.0 * std::f64::consts::PI / 180.0,
        mount_height: 0.6,
        far: 40.0,
    };

    /// Bytes of one RGB frame.
    pub fn frame_bytes(&self) -> usize {
        self.width * self.height * 3
    }

    /// Renders what the camera sees from `world_from_rover` into `rgb` (row-major, 3 bytes a
    /// pixel): sky above the horizon, sand with a 1 m grid below, rocks by depth.
    pub fn render(&self, terrain: &Terrain, world_from_rover: &Isometry2<f64>, rgb: &mut [u8]) {
        let (w, h) = (self.width, self.height);
        let focal = (w as f64 / 2.0) / (self.fov / 2.0).tan();
        let horizon = h as f64 / 2.0;
        let eye = Point2::from(world_from_rover.translation.vector);
        let eye_z = terrain.height(eye.x, eye.y) + self.mount_height;
        for col in 0..w {
            // Ray direction of this column in the world.
            let x_cam = (col as f64 + 0.5 - w as f64 / 2.0) / focal;
            let dir_rover = Vector2::new(1.0, -x_cam).normalize();
            let dir = world_from_rover.rotation * dir_rover;
            // Distance along the optical axis scales to distance along this ray.
            let stretch = (1.0 + x_cam * x_cam).sqrt();
            let hit = terrain.ray(&eye, &dir, self.far);
            for row in 0..h {
                let y_img = (row as f64 + 0.5 - horizon) / focal;
                let px = &mut rgb[(row * w + col) * 3..(row * w + col) * 3 + 3];
                // The rock, if this pixel's ray meets it below its top.
                if let Some((d, rock)) = hit {
                    let depth = d / stretch;
                    let top = terrain.height(rock.center.x, rock.center.y) + rock.height;
                    let ray_z = eye_z - y_img * depth;
                    let ground_z = terrain.height(rock.center.x, rock.center.y);
                    if ray_z <= top && ray_z >= ground_z - 0.2 {
                        let shade = (1.0 - d / self.far).clamp(0.2, 1.0);
                        let v = (110.0 * shade) as u8;
                        px.copy_from_slice(&[
                            v,
                            (f64::from(v) * 0.9) as u8,
                            (f64::from(v) * 0.8) as u8,
                        ]);
                        continue;
                    }
                }
                if y_img <= 0.0 {
                    // Sky: lighter towards the horizon.
                    let t = (row as f64 / horizon).clamp(0.0, 1.0);
                    px.copy_from_slice(&[
                        (180.0 + 40.0 * t) as u8,
                        (150.0 + 40.0 * t) as u8,
                        (120.0 + 30.0 * t) as u8,
                    ]);
                    continue;
                }
                // Ground: where the ray meets the (locally flat) terrain.
                let depth = self.mount_height / y_img;
                if depth > self.far {
                    px.copy_from_slice(&[200, 160, 120]);
                    continue;
                }
                let g = eye + dir * depth * stretch;
                let z = terrain.height(g.x, g.y);
                let grid = (g.x - g.x.round()).abs() < 0.03 || (g.y - g.y.round()).abs() < 0.03;
                let fade = (1.0 - depth / self.far).clamp(0.0, 1.0);
                let base = 150.0 + 120.0 * z;
                let (r, gr, b) = if grid {
                    (base * 0.6, base * 0.45, base * 0.35)
                } else {
                    (base + 40.0, base * 0.75, base * 0.5)
                };
                let mix =
                    |c: f64, far: f64| (c * fade + far * (1.0 - fade)).clamp(0.0, 255.0) as u8;
                px.copy_from_slice(&[mix(r, 200.0), mix(gr, 160.0), mix(b, 120.0)]);
            }
        }
    }
}

/// A small, seedable random source for sensor noise (xorshift64* and Box–Muller).
#[derive(Debug, Clone)]
pub struct Noise {
    state: u64,
}

impl Noise {
    pub fn new(seed: u64) -> Self {
        Self {
            state: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
        }
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        let x = self.state.wrapping_mul(0x2545_F491_4F6C_DD1D);
        (x >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Normal with mean 0 and standard deviation `sigma`.
    pub fn gauss(&mut self, sigma: f64) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_hit_the_nearest_rock_face() {
        let t = Terrain::mars_yard();
        // From the origin straight along +x: the rock at (9, 1.5) r 0.6 is off the line;
        // a ray aimed at its centre hits its face.
        let origin = Point2::new(0.0, 0.0);
        let to = Vector2::new(9.0, 1.5);
        let (d, rock) = t.ray(&origin, &to.normalize(), 20.0).unwrap();
        assert!((d - (to.norm() - 0.6)).abs() < 1e-9);
        assert_eq!(rock.center, Point2::new(9.0, 1.5));
        assert!(t.ray(&origin, &Vector2::x(), 20.0).is_none());
        assert!(t.collides(&Point2::new(9.0, 1.0)));
        assert!(!t.collides(&Point2::new(0.0, 0.0)));
    }

    #[test]
    fn camera_sees_sky_ground_and_a_rock_ahead() {
        let t = Terrain::mars_yard();
        let cam = CameraModel::BEETLE;
        let mut rgb = vec![0u8; cam.frame_bytes()];
        // Facing the rock at (9, 1.5) from 4 m away.
        let at = Point2::new(9.0 - 4.0, 1.5);
        let pose = Isometry2::new(at.coords, 0.0);
        cam.render(&t, &pose, &mut rgb);
        let px = |rgb: &[u8], col: usize, row: usize| {
            let i = (row * cam.width + col) * 3;
            [rgb[i], rgb[i + 1], rgb[i + 2]]
        };
        let sky = px(&rgb, 10, 5);
        let ground = px(&rgb, 10, cam.height - 5);
        let rock = px(&rgb, cam.width / 2, cam.height / 2 + 2);
        assert!(
            sky[2] > 100 && sky != ground,
            "sky {sky:?} ground {ground:?}"
        );
        assert!(rock[0] < 110 && rock != ground, "rock {rock:?}");
        // Turned away, the centre is ground or sky, not rock.
        cam.render(
            &t,
            &Isometry2::new(at.coords, std::f64::consts::PI),
            &mut rgb,
        );
        assert_ne!(px(&rgb, cam.width / 2, cam.height / 2 + 2), rock);
    }

    #[test]
    fn noise_has_the_asked_spread() {
        let mut n = Noise::new(7);
        let xs: Vec<f64> = (0..20000).map(|_| n.gauss(0.5)).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let sd = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64).sqrt();
        assert!(mean.abs() < 0.02 && (sd - 0.5).abs() < 0.02, "{mean} {sd}");
    }
}
