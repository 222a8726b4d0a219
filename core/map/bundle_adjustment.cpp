#include "kestrel/core/bundle_adjustment.hpp"

#include <Eigen/Cholesky>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <algorithm>
#include <cmath>
#include <unordered_map>

#include "kestrel/core/levenberg_marquardt.hpp"
#include "kestrel/core/so3.hpp"

namespace kestrel::core {

// The reduced camera system of a large problem, in 6x6 blocks: one per free
// pose on the diagonal, one per pair of free poses that share a point below
// it. The pattern is built once per solve and analysed once; each LM step
// only refills the values and factorises.
struct BaSparse {
  Eigen::SparseMatrix<double> S;  // lower triangle
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower, Eigen::AMDOrdering<int>> ldlt;
  std::vector<Eigen::Matrix<double, 6, 6>> blocks;  // [0, nf): diagonal; then (row > col)
  std::vector<int32_t> block_row, block_col;
  std::vector<int32_t> pair_block;  // per observation pair, in the Schur loop's order
  std::vector<int32_t> rel_block;   // per relative-pose factor between two free poses (else -1)
  std::vector<int32_t> base;        // per block and column: the value index of its first stored row
  Eigen::VectorXd rhs;
};

namespace {

// The block pattern of the reduced system for the observation pairs the
// Schur loop visits (same order), its sparse matrix and symbolic analysis.
void build_sparse_pattern(const BaProblem& pb, const BaScratch& s, size_t nq, int nf, BaSparse& sp) {
  sp.blocks.assign(static_cast<size_t>(nf), Eigen::Matrix<double, 6, 6>::Zero());
  sp.block_row.resize(static_cast<size_t>(nf));
  sp.block_col.resize(static_cast<size_t>(nf));
  for (int f = 0; f < nf; ++f)
    sp.block_row[static_cast<size_t>(f)] = sp.block_col[static_cast<size_t>(f)] = f;
  std::unordered_map<uint64_t, int32_t> index;
  auto block_of = [&](int fi, int fj) {
    const int hi = std::max(fi, fj), lo = std::min(fi, fj);
    const uint64_t key = static_cast<uint64_t>(hi) * static_cast<uint64_t>(nf) + static_cast<uint64_t>(lo);
    auto it = index.find(key);
    if (it == index.end()) {
      it = index.emplace(key, static_cast<int32_t>(sp.blocks.size())).first;
      sp.blocks.emplace_back(Eigen::Matrix<double, 6, 6>::Zero());
      sp.block_row.push_back(hi);
      sp.block_col.push_back(lo);
    }
    return it->second;
  };
  sp.pair_block.clear();
  for (size_t a = 0; a < nq; ++a) {
    for (int32_t e = s.point_begin[a]; e < s.point_begin[a + 1]; ++e) {
      const int fi = s.free_of[static_cast<size_t>(e)];
      if (fi < 0) continue;
      for (int32_t e2 = s.point_begin[a]; e2 <= e; ++e2) {
        const int fj = s.free_of[static_cast<size_t>(e2)];
        if (fj < 0) continue;
        if (fi == fj) {
          sp.pair_block.push_back(fi);
          continue;
        }
        sp.pair_block.push_back(block_of(fi, fj));
      }
    }
  }
  sp.rel_block.assign(pb.relative.size(), -1);
  for (size_t r = 0; r < pb.relative.size(); ++r) {
    const int fa = s.free_index[static_cast<size_t>(pb.relative[r].a)];
    const int fb = s.free_index[static_cast<size_t>(pb.relative[r].b)];
    if (fa >= 0 && fb >= 0 && fa != fb) sp.rel_block[r] = block_of(fa, fb);
  }
  std::vector<Eigen::Triplet<double>> t;
  t.reserve(sp.blocks.size() * 36);
  for (size_t b = 0; b < sp.blocks.size(); ++b) {
    const int r0 = 6 * sp.block_row[b], c0 = 6 * sp.block_col[b];
    const bool diag = static_cast<int>(b) < nf;
    for (int c = 0; c < 6; ++c)
      for (int r = diag ? c : 0; r < 6; ++r) t.emplace_back(r0 + r, c0 + c, 0.0);
  }
  sp.S.resize(6 * nf, 6 * nf);
  sp.S.setFromTriplets(t.begin(), t.end());
  sp.S.makeCompressed();
  sp.base.resize(sp.blocks.size() * 6);
  const int* outer = sp.S.outerIndexPtr();
  const int* inner = sp.S.innerIndexPtr();
  for (size_t b = 0; b < sp.blocks.size(); ++b) {
    const int r0 = 6 * sp.block_row[b], c0 = 6 * sp.block_col[b];
    const bool diag = static_cast<int>(b) < nf;
    for (int c = 0; c < 6; ++c) {
      const int first = diag ? r0 + c : r0;
      sp.base[b * 6 + static_cast<size_t>(c)] = static_cast<int32_t>(
          std::lower_bound(inner + outer[c0 + c], inner + outer[c0 + c + 1], first) - inner);
    }
  }
  sp.ldlt.analyzePattern(sp.S);
}

// The blocks into the matrix's lower triangle.
void scatter_sparse(int nf, BaSparse& sp) {
  double* val = sp.S.valuePtr();
  for (size_t b = 0; b < sp.blocks.size(); ++b) {
    const bool diag = static_cast<int>(b) < nf;
    const Eigen::Matrix<double, 6, 6>& B = sp.blocks[b];
    for (int c = 0; c < 6; ++c) {
      double* dst = val + sp.base[b * 6 + static_cast<size_t>(c)];
      for (int r = diag ? c : 0; r < 6; ++r) *dst++ = B(r, c);
    }
  }
}

constexpr double kMinZ_m = 1e-3;  // the same clamp as the Ceres cost: a point behind the camera stays finite
// Ceres' trust radius bounds (1e16 and 1e-32) as damping bounds: mu never
// reaches 0 (a point without observations would give inf x 0) nor infinity.
constexpr double kMinMu = 1e-16, kMaxMu = 1e32;

struct Linearised {
  bool depth = false;
  Eigen::Vector3d r = Eigen::Vector3d::Zero();
  Eigen::Matrix<double, 3, 6> J_pose = Eigen::Matrix<double, 3, 6>::Zero();
  Eigen::Matrix3d J_point = Eigen::Matrix3d::Zero();
};

// Residual and Jacobians under the left perturbation R <- Exp(dtheta) R,
// t <- t + dt, p <- p + dp (Ceres' quaternion manifold perturbs on the left
// too, so both solvers take the same steps up to the step control).
void linearise(const BaProblem& pb, const BaObservation& o, Linearised& L) {
  const BaPose& P = pb.poses[static_cast<size_t>(o.pose)];
  const Eigen::Vector3d Rp = P.R_CM * pb.points_M[static_cast<size_t>(o.point)];
  const Eigen::Vector3d c = Rp + P.t_CM;
  const bool clamped = c.z() < kMinZ_m;
  const double z = clamped ? kMinZ_m : c.z();
  const double iz = 1.0 / z;
  L.depth = o.depth_m > 0;
  L.r.x() = (pb.K.fx * c.x() * iz + pb.K.cx - o.u_px) * o.inv_sigma_px;
  L.r.y() = (pb.K.fy * c.y() * iz + pb.K.cy - o.v_px) * o.inv_sigma_px;
  L.r.z() = L.depth ? (c.z() - o.depth_m) * o.inv_sigma_z : 0.0;  // no depth: a zero row
  Eigen::Matrix3d dr_dc = Eigen::Matrix3d::Zero();
  dr_dc(0, 0) = pb.K.fx * iz * o.inv_sigma_px;
  dr_dc(1, 1) = pb.K.fy * iz * o.inv_sigma_px;
  if (!clamped) {
    dr_dc(0, 2) = -pb.K.fx * c.x() * iz * iz * o.inv_sigma_px;
    dr_dc(1, 2) = -pb.K.fy * c.y() * iz * iz * o.inv_sigma_px;
  }
  if (L.depth) dr_dc(2, 2) = o.inv_sigma_z;
  L.J_pose.leftCols<3>() = -dr_dc * so3::hat(Rp);
  L.J_pose.rightCols<3>() = dr_dc;
  L.J_point = dr_dc * P.R_CM;
}

// The LM diagonal D of one parameter, from its diag(J'J), in Ceres' bounds.
double damping(double jtj) { return std::clamp(jtj, 1e-6, 1e32); }

// Huber on the squared whitened error s, as ceres::HuberLoss: rho(s) = s
// inside a^2, 2 a sqrt(s) - a^2 outside; rho'(s) is the IRLS weight.
double huber_rho(double s, double a) { return s <= a * a ? s : 2.0 * a * std::sqrt(s) - a * a; }
double huber_weight(double s, double a) { return s <= a * a ? 1.0 : a / std::sqrt(s); }

Eigen::Vector3d gravity_residual(const BaProblem& pb, const BaPose& P) {
  return (-P.R_CM.col(2) - P.g_C) * pb.gravity_inv_sigma;
}

bool gravity_on(const BaProblem& pb, const BaPose& P) {
  return pb.gravity_inv_sigma > 0 && P.has_gravity && !P.fixed;
}

}  // namespace

double ba_chi2(const BaProblem& pb, const BaObservation& o) {
  const BaPose& P = pb.poses[static_cast<size_t>(o.pose)];
  const Eigen::Vector3d c = P.R_CM * pb.points_M[static_cast<size_t>(o.point)] + P.t_CM;
  if (c.z() < kMinZ_m) return 1e30;
  const double eu = (pb.K.fx * c.x() / c.z() + pb.K.cx - o.u_px) * o.inv_sigma_px;
  const double ev = (pb.K.fy * c.y() / c.z() + pb.K.cy - o.v_px) * o.inv_sigma_px;
  double e = eu * eu + ev * ev;
  if (o.depth_m > 0) {
    const double ez = (c.z() - o.depth_m) * o.inv_sigma_z;
    e += ez * ez;
  }
  return e;
}

void ba_observation_residual(const BaProblem& pb, const BaObservation& o, Eigen::Vector3d* r,
                             Eigen::Matrix<double, 3, 6>* J_pose, Eigen::Matrix3d* J_point) {
  Linearised L;
  linearise(pb, o, L);
  *r = L.r;
  *J_pose = L.J_pose;
  *J_point = L.J_point;
}

Eigen::Vector3d ba_gravity_residual(const BaProblem& pb, const BaPose& P, Eigen::Matrix3d* J_rot) {
  // Exp(dtheta) R: -Exp(dtheta) R e_z = -R e_z + hat(R e_z) dtheta to first order.
  if (J_rot != nullptr) *J_rot = -so3::hat(-P.R_CM.col(2)) * pb.gravity_inv_sigma;
  return gravity_residual(pb, P);
}

void ba_relative_residual(const BaProblem& pb, const BaRelativePose& e, Eigen::Matrix<double, 6, 1>* r,
                          Eigen::Matrix<double, 6, 6>* J_a, Eigen::Matrix<double, 6, 6>* J_b) {
  const BaPose& A = pb.poses[static_cast<size_t>(e.a)];
  const BaPose& B = pb.poses[static_cast<size_t>(e.b)];
  // T_CaCb = T_CaM T_CbM^-1.
  const Eigen::Matrix3d R = A.R_CM * B.R_CM.transpose();
  const Eigen::Vector3d Rt_b = R * B.t_CM;
  const Eigen::Vector3d t = A.t_CM - Rt_b;
  const Eigen::Vector3d r_rot = so3::Log(e.R_ab.transpose() * R);
  r->head<3>() = r_rot * e.inv_sigma_rad;
  r->tail<3>() = (t - e.t_ab) * e.inv_sigma_m;
  if (J_a == nullptr || J_b == nullptr) return;
  // Exp(da) R_a: Log(Z' Exp(da) R) = Log(Z' R Exp(R' da)); R_b^T Exp(-db): Log(Z' R Exp(-db)).
  const Eigen::Matrix3d Jr_inv = so3::right_jacobian_inv(r_rot);
  J_a->setZero();
  J_b->setZero();
  J_a->block<3, 3>(0, 0) = Jr_inv * R.transpose() * e.inv_sigma_rad;
  J_b->block<3, 3>(0, 0) = -Jr_inv * e.inv_sigma_rad;
  J_a->block<3, 3>(3, 0) = so3::hat(Rt_b) * e.inv_sigma_m;
  J_a->block<3, 3>(3, 3) = Eigen::Matrix3d::Identity() * e.inv_sigma_m;
  J_b->block<3, 3>(3, 0) = -R * so3::hat(B.t_CM) * e.inv_sigma_m;
  J_b->block<3, 3>(3, 3) = -R * e.inv_sigma_m;
}

double ba_cost(const BaProblem& pb) {
  double cost = 0;
  for (const BaObservation& o : pb.obs) {
    if (!o.enabled) continue;
    const BaPose& P = pb.poses[static_cast<size_t>(o.pose)];
    const Eigen::Vector3d c = P.R_CM * pb.points_M[static_cast<size_t>(o.point)] + P.t_CM;
    const double iz = 1.0 / std::max(c.z(), kMinZ_m);
    const double eu = (pb.K.fx * c.x() * iz + pb.K.cx - o.u_px) * o.inv_sigma_px;
    const double ev = (pb.K.fy * c.y() * iz + pb.K.cy - o.v_px) * o.inv_sigma_px;
    const double ez = o.depth_m > 0 ? (c.z() - o.depth_m) * o.inv_sigma_z : 0.0;
    cost += huber_rho(eu * eu + ev * ev + ez * ez, pb.huber);
  }
  for (const BaPose& P : pb.poses)
    if (gravity_on(pb, P)) cost += gravity_residual(pb, P).squaredNorm();
  Eigen::Matrix<double, 6, 1> r;
  for (const BaRelativePose& e : pb.relative) {
    ba_relative_residual(pb, e, &r, nullptr, nullptr);
    cost += r.squaredNorm();
  }
  return 0.5 * cost;
}

namespace {

// The bundle adjustment as the problem of the one Levenberg-Marquardt loop
// (levenberg_marquardt.hpp): the free poses' 6-vectors are the unknowns of
// the reduced camera system, the points are Schur-eliminated in solve() and
// recovered by back-substitution.
struct BaLm {
  BaProblem& pb;
  BaScratch& s;
  const size_t np = 0, nq = 0;
  const int nf = 0, dim = 0;
  const bool sparse = false;
  Linearised L;

  void linearize();
  bool solve(double mu, lm::Step* step);
  double try_step();
  void accept() {}
  void reject();

 private:
  void fill_damped_system(double mu);
  bool back_substitute(double mu, lm::Step* step);
};

void BaLm::linearize() {
  for (Eigen::Matrix<double, 6, 6>& Hf : s.H_diag) Hf.setZero();
  s.g.setZero();
  for (size_t a = 0; a < nq; ++a) {
    Eigen::Matrix3d& V = s.V[a];
    Eigen::Vector3d& ga = s.g_point[a];
    V.setZero();
    ga.setZero();
    for (int32_t e = s.point_begin[a]; e < s.point_begin[a + 1]; ++e) {
      const BaObservation& o = pb.obs[static_cast<size_t>(s.by_point[static_cast<size_t>(e)])];
      linearise(pb, o, L);
      // Fixed 3-row blocks (a depth-less row is zero) keep Eigen's
      // products fixed-size: dynamic row counts cost twice the time.
      const Eigen::Vector3d& r = L.r;
      const double w = huber_weight(r.squaredNorm(), pb.huber);
      const Eigen::Matrix3d& Jp = L.J_point;
      V.noalias() += w * Jp.transpose() * Jp;
      ga.noalias() += w * Jp.transpose() * r;
      const int f = s.free_of[static_cast<size_t>(e)];
      if (f < 0) continue;
      const Eigen::Matrix<double, 3, 6>& Jc = L.J_pose;
      s.H_diag[static_cast<size_t>(f)].noalias() += w * Jc.transpose() * Jc;
      s.g.segment<6>(6 * f).noalias() += w * Jc.transpose() * r;
      s.W[static_cast<size_t>(e)].noalias() = w * Jc.transpose() * Jp;
    }
  }
  for (size_t i = 0; i < np; ++i) {
    const BaPose& P = pb.poses[i];
    if (!gravity_on(pb, P)) continue;
    const int f = s.free_index[i];
    Eigen::Matrix3d J;
    const Eigen::Vector3d r = ba_gravity_residual(pb, P, &J);
    s.H_diag[static_cast<size_t>(f)].topLeftCorner<3, 3>().noalias() += J.transpose() * J;
    s.g.segment<3>(6 * f).noalias() += J.transpose() * r;
  }
  for (size_t k = 0; k < pb.relative.size(); ++k) {
    const BaRelativePose& e = pb.relative[k];
    Eigen::Matrix<double, 6, 1> r;
    Eigen::Matrix<double, 6, 6> Ja, Jb;
    ba_relative_residual(pb, e, &r, &Ja, &Jb);
    const int fa = s.free_index[static_cast<size_t>(e.a)], fb = s.free_index[static_cast<size_t>(e.b)];
    if (fa >= 0) {
      s.H_diag[static_cast<size_t>(fa)].noalias() += Ja.transpose() * Ja;
      s.g.segment<6>(6 * fa).noalias() += Ja.transpose() * r;
    }
    if (fb >= 0) {
      s.H_diag[static_cast<size_t>(fb)].noalias() += Jb.transpose() * Jb;
      s.g.segment<6>(6 * fb).noalias() += Jb.transpose() * r;
    }
    s.H_rel[k].noalias() = Ja.transpose() * Jb;
  }
}

// The damped reduced camera system S dx = -b, lower triangle only: the
// poses' blocks, the relative-pose factors' (a, b) blocks, and minus each
// point's W V^-1 W'.
void BaLm::fill_damped_system(double mu) {
  if (sparse) {
    BaSparse& sp = *s.sparse;
    for (size_t b = static_cast<size_t>(nf); b < sp.blocks.size(); ++b) sp.blocks[b].setZero();
    for (int f = 0; f < nf; ++f) {
      Eigen::Matrix<double, 6, 6>& D = sp.blocks[static_cast<size_t>(f)];
      D = s.H_diag[static_cast<size_t>(f)];
      for (int d = 0; d < 6; ++d) D(d, d) += mu * damping(s.H_diag[static_cast<size_t>(f)](d, d));
    }
  } else {
    s.S.setZero();
    for (int f = 0; f < nf; ++f) {
      s.S.block<6, 6>(6 * f, 6 * f) = s.H_diag[static_cast<size_t>(f)];
      for (int d = 0; d < 6; ++d)
        s.S(6 * f + d, 6 * f + d) += mu * damping(s.H_diag[static_cast<size_t>(f)](d, d));
    }
  }
  for (size_t k = 0; k < pb.relative.size(); ++k) {
    const int fa = s.free_index[static_cast<size_t>(pb.relative[k].a)];
    const int fb = s.free_index[static_cast<size_t>(pb.relative[k].b)];
    if (fa < 0 || fb < 0 || fa == fb) continue;
    if (sparse) {
      Eigen::Matrix<double, 6, 6>& T = s.sparse->blocks[static_cast<size_t>(s.sparse->rel_block[k])];
      if (fa > fb) {
        T += s.H_rel[k];
      } else {
        T += s.H_rel[k].transpose();
      }
    } else if (fa > fb) {
      s.S.block<6, 6>(6 * fa, 6 * fb) += s.H_rel[k];
    } else {
      s.S.block<6, 6>(6 * fb, 6 * fa) += s.H_rel[k].transpose();
    }
  }
  s.b = s.g;
  size_t pair = 0;
  for (size_t a = 0; a < nq; ++a) {
    Eigen::Matrix3d Vd = s.V[a];
    for (int d = 0; d < 3; ++d) Vd(d, d) += mu * damping(s.V[a](d, d));
    s.V_inv[a] = Vd.inverse();
    for (int32_t e = s.point_begin[a]; e < s.point_begin[a + 1]; ++e) {
      const int fi = s.free_of[static_cast<size_t>(e)];
      if (fi < 0) continue;
      const Eigen::Matrix<double, 6, 3> WV = s.W[static_cast<size_t>(e)] * s.V_inv[a];
      s.b.segment<6>(6 * fi).noalias() -= WV * s.g_point[a];
      for (int32_t e2 = s.point_begin[a]; e2 <= e; ++e2) {
        const int fj = s.free_of[static_cast<size_t>(e2)];
        if (fj < 0) continue;
        const Eigen::Matrix<double, 6, 6> B = WV * s.W[static_cast<size_t>(e2)].transpose();
        if (sparse) {
          Eigen::Matrix<double, 6, 6>& T =
              s.sparse->blocks[static_cast<size_t>(s.sparse->pair_block[pair++])];
          if (fi > fj) {
            T -= B;
          } else if (fi < fj) {
            T -= B.transpose();
          } else {
            T -= B;
            if (e2 != e) T -= B.transpose();
          }
        } else if (fi > fj) {
          s.S.block<6, 6>(6 * fi, 6 * fj) -= B;
        } else if (fi < fj) {
          s.S.block<6, 6>(6 * fj, 6 * fi) -= B.transpose();
        } else {
          s.S.block<6, 6>(6 * fi, 6 * fi) -= B;
          if (e2 != e) s.S.block<6, 6>(6 * fi, 6 * fi) -= B.transpose();  // one keyframe, two observations
        }
      }
    }
  }
}

// The points' steps, the model's decrease (with (A + mu D) x = -g it is
// -g'x - x'Ax/2 = (-g'x + mu x'Dx) / 2) and Ceres' parameter tolerance
// (1e-8): a step too small to change the parameters.
bool BaLm::back_substitute(double mu, lm::Step* step) {
  double gx = dim > 0 ? s.g.dot(s.dx) : 0.0, xDx = 0;
  for (int d = 0; d < dim; ++d)
    xDx += damping(s.H_diag[static_cast<size_t>(d / 6)](d % 6, d % 6)) * s.dx[d] * s.dx[d];
  for (size_t a = 0; a < nq; ++a) {
    Eigen::Vector3d rhs = s.g_point[a];
    for (int32_t e = s.point_begin[a]; e < s.point_begin[a + 1]; ++e) {
      const int fi = s.free_of[static_cast<size_t>(e)];
      if (fi >= 0) rhs.noalias() += s.W[static_cast<size_t>(e)].transpose() * s.dx.segment<6>(6 * fi);
    }
    s.d_point[a] = -s.V_inv[a] * rhs;
    if (!s.d_point[a].allFinite()) return false;
    gx += s.g_point[a].dot(s.d_point[a]);
    for (int d = 0; d < 3; ++d) xDx += damping(s.V[a](d, d)) * s.d_point[a][d] * s.d_point[a][d];
  }
  step->predicted_decrease = 0.5 * (-gx + mu * xDx);
  double step2 = dim > 0 ? s.dx.squaredNorm() : 0.0, x2 = 0;
  for (size_t a = 0; a < nq; ++a) {
    step2 += s.d_point[a].squaredNorm();
    x2 += pb.points_M[a].squaredNorm();
  }
  for (size_t i = 0; i < np; ++i)
    if (s.free_index[i] >= 0) x2 += pb.poses[i].t_CM.squaredNorm() + 3.0;  // + the rotation's own size
  step->negligible = std::sqrt(step2) <= 1e-8 * (std::sqrt(x2) + 1e-8);
  return true;
}

bool BaLm::solve(double mu, lm::Step* step) {
  fill_damped_system(mu);
  bool solved = true;
  if (dim > 0 && sparse) {
    BaSparse& sp = *s.sparse;
    scatter_sparse(nf, sp);
    sp.ldlt.factorize(sp.S);
    solved = sp.ldlt.info() == Eigen::Success;
    if (solved) {
      sp.rhs = -s.b;
      s.dx = sp.ldlt.solve(sp.rhs);
      solved = sp.ldlt.info() == Eigen::Success && s.dx.allFinite();
    }
  } else if (dim > 0) {
    Eigen::LDLT<Eigen::MatrixXd, Eigen::Lower> ldlt(s.S);
    s.dx = ldlt.solve(-s.b);
    solved = ldlt.info() == Eigen::Success && s.dx.allFinite();
  }
  return solved && back_substitute(mu, step);
}

double BaLm::try_step() {
  for (size_t i = 0; i < np; ++i) {
    s.R_old[i] = pb.poses[i].R_CM;
    s.t_old[i] = pb.poses[i].t_CM;
    const int f = s.free_index[i];
    if (f < 0) continue;
    pb.poses[i].R_CM = so3::Exp(s.dx.segment<3>(6 * f)) * pb.poses[i].R_CM;
    pb.poses[i].t_CM += s.dx.segment<3>(6 * f + 3);
  }
  for (size_t a = 0; a < nq; ++a) {
    s.points_old[a] = pb.points_M[a];
    pb.points_M[a] += s.d_point[a];
  }
  return ba_cost(pb);
}

void BaLm::reject() {
  for (size_t i = 0; i < np; ++i) {
    pb.poses[i].R_CM = s.R_old[i];
    pb.poses[i].t_CM = s.t_old[i];
  }
  for (size_t a = 0; a < nq; ++a) pb.points_M[a] = s.points_old[a];
}

}  // namespace

BaResult solve_bundle_adjustment(BaProblem& pb, int max_iterations, BaScratch& s) {
  BaResult res;
  const size_t np = pb.poses.size(), nq = pb.points_M.size(), no = pb.obs.size();
  s.free_index.assign(np, -1);
  int nf = 0;
  for (size_t i = 0; i < np; ++i)
    if (!pb.poses[i].fixed) s.free_index[i] = nf++;
  const int dim = 6 * nf;

  // Observations grouped by point (counting sort): the Schur complement is a
  // sum over each point's observation pairs.
  s.point_begin.assign(nq + 1, 0);
  for (const BaObservation& o : pb.obs)
    if (o.enabled) ++s.point_begin[static_cast<size_t>(o.point) + 1];
  for (size_t a = 0; a < nq; ++a) s.point_begin[a + 1] += s.point_begin[a];
  s.by_point.resize(static_cast<size_t>(s.point_begin[nq]));
  s.cursor.assign(s.point_begin.begin(), s.point_begin.end() - 1);
  for (size_t k = 0; k < no; ++k) {
    const BaObservation& o = pb.obs[k];
    if (o.enabled)
      s.by_point[static_cast<size_t>(s.cursor[static_cast<size_t>(o.point)]++)] = static_cast<int32_t>(k);
  }
  s.free_of.resize(s.by_point.size());
  for (size_t e = 0; e < s.by_point.size(); ++e)
    s.free_of[e] = s.free_index[static_cast<size_t>(pb.obs[static_cast<size_t>(s.by_point[e])].pose)];
  s.W.resize(s.by_point.size());
  s.V.resize(nq);
  s.V_inv.resize(nq);
  s.g_point.resize(nq);
  s.d_point.resize(nq);
  s.points_old.resize(nq);
  s.R_old.resize(np);
  s.t_old.resize(np);
  s.H_diag.resize(static_cast<size_t>(nf));
  s.H_rel.resize(pb.relative.size());
  const bool sparse = nf > s.sparse_from_free_poses;
  if (sparse) {
    if (!s.sparse) s.sparse = std::make_shared<BaSparse>();
    build_sparse_pattern(pb, s, nq, nf, *s.sparse);
  } else {
    s.S.resize(dim, dim);
  }
  s.g.resize(dim);
  s.b.resize(dim);
  s.dx.resize(dim);

  const double cost = ba_cost(pb);
  res.initial_cost = res.final_cost = cost;
  if (!std::isfinite(cost)) return res;
  res.usable = true;

  // Ceres' rules and defaults, so that both solvers land on the same minimum:
  // the diagonal scaled by mu = 1 / trust radius (1e4 at the start) and
  // clamped to [1e-6, 1e32]; a step is taken when it achieves 1e-3 of the
  // model's decrease; the function tolerance (1e-6) counts every step tried;
  // a negligible step, or a model with nothing left to gain (1e-12 of the
  // cost), ends the solve before it is tried.
  lm::Rules rules;
  rules.max_iterations = max_iterations;
  rules.min_lambda = kMinMu;
  rules.max_lambda = kMaxMu;
  rules.min_relative_decrease = 1e-3;
  rules.function_tolerance = 1e-6;
  rules.function_tolerance_on_rejected_steps = true;
  rules.min_model_decrease = 1e-12;
  rules.try_negligible_step = false;
  BaLm problem{pb, s, np, nq, nf, dim, sparse, Linearised{}};
  const lm::Outcome out = lm::minimize(problem, cost, rules);
  res.iterations = out.iterations;
  res.final_cost = out.cost;
  return res;
}

}  // namespace kestrel::core
