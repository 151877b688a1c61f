"""Quasi-static total-Lagrangian FEA of a keyed grid mesh in dolfinx 0.5: residual stress release + body force.

Read top to bottom as physics: mesh (gmsh -> dolfinx, keys kept), spaces (Q2 displacement), kinematics,
energy Pi(u; t) = int W(F) + t S0 : E dV - t int b . u dV with only the terms the scene turns on, the
fixed face, then Newton (PETSc SNES, MUMPS) over adaptive pseudo-time increments that land exactly on the
frame times. Units: mm, N, MPa, s.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from fea_factory.design import Design
from fea_factory.material import ReducedPolynomial
from fea_factory.mesh import KeyedMesh, add_to_gmsh
from fea_factory.residual_stress import initial_stress
from fea_factory.scene import Scene

log = logging.getLogger(__name__)
VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # xx, yy, zz, xy, xz, yz


@dataclass(frozen=True)
class SolverSettings:
    """conf/solver/*.yaml"""

    increments: int = 100
    save_every: int = 10
    adaptive: bool = True
    max_cutbacks: int = 8
    grow: float = 2.0
    easy_iterations: int = 4
    degree: int = 2
    quadrature_degree: int = 4
    stress_quadrature_degree: int = 3
    max_it: int = 15
    force_tol: float = 1e-5
    line_search: str = "basic"
    linear_solver: str = "direct"
    predictor: str = "quadratic"
    stabilize: bool = False
    stabilize_max_steps: int = 60
    stabilize_accept_mm: float = 0.1
    jit_compile_args: tuple = ("-O3", "-march=native", "-g0",  # as conf/solver/default.yaml
                               "-fno-math-errno", "-fno-trapping-math")

    def __post_init__(self) -> None:
        checks = [
            ("increments", self.increments >= 1, ">= 1"),
            ("save_every", 1 <= self.save_every <= self.increments and self.increments % self.save_every == 0,
             "in [1, increments] and dividing increments"),
            ("max_cutbacks", 0 <= self.max_cutbacks <= 20, "in [0, 20]"),
            ("grow", 1.0 <= self.grow <= 4.0, "in [1, 4]"),
            ("degree", self.degree in (1, 2), "1 or 2"),
            ("quadrature_degree", 1 <= self.quadrature_degree <= 8, "in [1, 8]"),
            ("newton.max_it", 1 <= self.max_it <= 200, "in [1, 200]"),
            ("newton.force_tol", 0 < self.force_tol < 1e-2, "in (0, 1e-2)"),
            ("newton.line_search", self.line_search in ("basic", "bt"), "basic | bt (cp and l2 diverge here)"),
            ("linear_solver", self.linear_solver in ("direct", "iterative"), "direct | iterative"),
            ("predictor", self.predictor in ("quadratic", "linear", "none"), "quadratic | linear | none"),
            ("stabilize_max_steps", 1 <= self.stabilize_max_steps <= 10000, "in [1, 10000]"),
            ("stabilize_accept_mm", 0 < self.stabilize_accept_mm <= 10, "in (0, 10] mm"),
        ]
        for name, ok, allowed in checks:
            if not ok:
                raise ValueError(f"solver.{name} = {getattr(self, name.split('.')[-1], '?')}: must be {allowed}")

    @classmethod
    def from_mapping(cls, m) -> "SolverSettings":
        flat = {k: m[k] for k in cls.__dataclass_fields__ if k in m}
        if "jit_compile_args" in flat:
            flat["jit_compile_args"] = tuple(str(a) for a in flat["jit_compile_args"])
        newton = m.get("newton", {}) or {}
        flat.update({k: newton[k] for k in ("max_it", "force_tol", "line_search") if k in newton})
        return cls(**flat)

    @property
    def frame_times(self) -> np.ndarray:
        n = self.increments // self.save_every
        return np.linspace(0.0, 1.0, n + 1)


@dataclass
class Frames:
    """Saved frames in key order (rank 0 only): t [F], node_xyz [F, N, 3] mm, stress [F, C, Q, 6] MPa."""

    t: list = field(default_factory=list)
    node_xyz: list = field(default_factory=list)
    stress: list = field(default_factory=list)
    quad_points: np.ndarray | None = None  # [Q, 3] reference hex coordinates (i, j, k directions)
    quad_weights: np.ndarray | None = None


def stress_quadrature(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Points [Q, 3] in [0, 1]^3 and weights [Q] of the hex rule the stress is sampled at (episode quad_points)."""
    import basix

    qp, qw = basix.make_quadrature(basix.CellType.hexahedron, int(degree))
    return np.asarray(qp), np.asarray(qw)


def predictor_weights(kind: str, dt: float, dt_prev: float | None, dt_prev2: float | None) -> tuple[float, float]:
    """The start of Newton at t + dt from the accepted states u (at t), u_1 (t - dt_prev), u_2 (t - dt_prev - dt_prev2):
    u + w1 (u_1 - u) + w2 (u_2 - u), the polynomial through them evaluated at t + dt. quadratic: through all three
    (exact for a path quadratic in t), linear: through u and u_1 (also quadratic's while only two states exist),
    none: u. A missing state (None: the start, or a jump across an instability) lowers the order."""
    if kind == "quadratic" and dt_prev and dt_prev2:
        a, b = dt_prev, dt_prev + dt_prev2  # the earlier states' distances back from t
        return -dt * (dt + b) / (a * (b - a)), dt * (dt + a) / (b * (b - a))
    if kind in ("linear", "quadratic") and dt_prev:
        return -dt / dt_prev, 0.0
    return 0.0, 0.0


class SolveFailure(RuntimeError):
    """A diverged episode: reported, never saved as data."""

    def __init__(self, reason: str, t: float, dt: float, increment: int, history: list):
        super().__init__(f"{reason} at t = {t:.5g} (dt = {dt:.3g}, increment {increment})")
        self.info = {"reason": reason, "t": t, "dt": dt, "increment": increment, "residual_history": history}
        self.last_xyz: np.ndarray | None = None  # [N, 3] key order, rank 0: the last state the solve reached
        self.last_t: float | None = None


SNES_REASONS = {-1: "function domain error", -2: "function count", -3: "linear solve failed",
                -4: "residual is NaN/Inf", -5: "max Newton iterations", -6: "line search failed",
                -7: "inner solve", -8: "local minimum", -9: "DIVERGED_DTOL", -10: "Jacobian domain",
                -11: "trust region"}


# ------------------------------------------------------------------------------------------ physics
def kinematics(u):
    import ufl

    I = ufl.Identity(3)
    F = ufl.variable(I + ufl.grad(u))
    E = 0.5 * (F.T * F - I)
    return F, E


def total_energy(material: ReducedPolynomial, u, S0, b, t, scene: Scene, dx):
    """Pi(u; t): stored energy, released residual stress, body force work; only the scene's terms."""
    import ufl

    F, E = kinematics(u)
    Pi = material.strain_energy(F) * dx
    if scene.residual_stress:
        Pi += t * ufl.inner(S0, E) * dx
    if scene.gravity:
        Pi -= t * ufl.dot(b, u) * dx
    return Pi


def cauchy_stress(material: ReducedPolynomial, u, S0, t, scene: Scene):
    """sigma = J^-1 P F^T with P = dW/dF (+ t F S0 from the initial stress)."""
    import ufl

    F, _ = kinematics(u)
    P = ufl.diff(material.strain_energy(F), F)
    if scene.residual_stress:
        P = P + t * F * S0
    return P * F.T / ufl.det(F)


# ------------------------------------------------------------------------------------------ solver
class GridSolver:
    """One episode: build once, then `run()` steps t from 0 to 1 and returns the frames (rank 0)."""

    def __init__(self, design: Design, mesh: KeyedMesh, material: ReducedPolynomial, scene: Scene,
                 S0_cells: np.ndarray, body_force: np.ndarray, settings: SolverSettings, comm,
                 clamp: str = "top_face"):
        if clamp not in ("top_face", "block"):
            raise ValueError(f"clamp = {clamp!r}: must be 'top_face' (the glued joint face) or 'block'")
        self.clamp = clamp
        self.design, self.keyed, self.material, self.scene, self.settings, self.comm = (
            design, mesh, material, scene, settings, comm)
        self.stats = {"wall_mesh_s": 0.0, "wall_jit_s": 0.0, "wall_solve_s": 0.0, "wall_output_s": 0.0,
                      "increment_t": [], "newton_iterations": [], "cutbacks": 0, "newton_failed": 0,
                      "linear_solves": 0}
        t0 = time.perf_counter()
        self._build_mesh()
        self.stats["wall_mesh_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self._build_forms(S0_cells, body_force)
        self.stats["wall_jit_s"] = time.perf_counter() - t0

    # mesh: gmsh model on rank 0, distributed by dolfinx; keys recovered from input node indices
    def _build_mesh(self) -> None:
        import gmsh
        from dolfinx.io import gmshio

        gmsh.initialize()
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            if self.comm.rank == 0:
                add_to_gmsh(self.keyed)
            self.msh, _, _ = gmshio.model_to_mesh(gmsh.model, self.comm, 0, gdim=3)
        finally:
            gmsh.finalize()
        msh = self.msh
        self.n_local_cells = msh.topology.index_map(3).size_local
        self.node_ids = np.asarray(msh.geometry.input_global_indices, dtype=np.int64)  # local geom node -> id
        geo = msh.geometry.dofmap.array.reshape(-1, 8)[: self.n_local_cells]
        lookup = {tuple(r): c for c, r in enumerate(np.sort(self.keyed.cell_nodes, axis=1).tolist())}
        self.cell_ids = np.array([lookup[tuple(r)] for r in np.sort(self.node_ids[geo], axis=1).tolist()],
                                 dtype=np.int64)
        self.geo_dofs = geo

    def _build_forms(self, S0_cells: np.ndarray, body_force: np.ndarray) -> None:
        import ufl
        from dolfinx import fem
        from petsc4py import PETSc

        msh, s = self.msh, self.settings
        # spaces
        self.V = fem.VectorFunctionSpace(msh, ("Lagrange", s.degree))
        T0 = fem.TensorFunctionSpace(msh, ("DG", 0))
        self.u = fem.Function(self.V, name="displacement")
        self.S0 = fem.Function(T0, name="initial_stress")
        dofs = T0.dofmap.list.array.reshape(-1)[: self.n_local_cells]
        S0_local = self.S0.x.array.reshape(-1, 9)
        S0_local[dofs] = S0_cells[self.cell_ids].reshape(-1, 9)
        self.S0.x.scatter_forward()
        self.t = fem.Constant(msh, PETSc.ScalarType(0.0))
        self.b = fem.Constant(msh, np.asarray(body_force, dtype=PETSc.ScalarType))
        dx = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": s.quadrature_degree})
        # energy, residual, tangent
        Pi = total_energy(self.material, self.u, self.S0, self.b, self.t, self.scene, dx)
        R = ufl.derivative(Pi, self.u, ufl.TestFunction(self.V))
        K = ufl.derivative(R, self.u, ufl.TrialFunction(self.V))
        jit = {"cffi_extra_compile_args": list(s.jit_compile_args)}
        self.R_form, self.K_form = fem.form(R, jit_params=jit), fem.form(K, jit_params=jit)
        self.Pi_form = fem.form(Pi, jit_params=jit) if s.line_search != "basic" else None
        self._plain_forms = (self.R_form, self.K_form, self.Pi_form)
        self._energy_parts = (Pi, dx, jit)  # the stabilized forms are built from these when first needed
        self._stabilized_forms = None
        self.bcs = [self._fixed_face_bc() if self.clamp == "top_face" else self._fixed_block_bc()]
        # outputs: Cauchy stress at Gauss points, node values through a Q1 space
        self.quad_points, self.quad_weights = stress_quadrature(s.stress_quadrature_degree)
        sig = cauchy_stress(self.material, self.u, self.S0, self.t, self.scene)
        self.stress_expr = fem.Expression(ufl.as_vector([sig[i, j] for i, j in VOIGT]), self.quad_points)
        self.V1 = fem.VectorFunctionSpace(msh, ("Lagrange", 1))
        self.u1 = fem.Function(self.V1)

    def _fixed_face_bc(self):
        """Clamp the top face (z = thickness) of the fixed joint: its facets, found by their node keys."""
        from dolfinx import fem, mesh as dmesh

        msh, keyed, d = self.msh, self.keyed, self.design
        nh = keyed.preset.nodes_height
        top = np.zeros(keyed.n_nodes, dtype=bool)
        top[keyed.joint_nodes[d.fixed_joint, :, :, nh - 1].reshape(-1)] = True
        msh.topology.create_connectivity(2, 0)
        msh.topology.create_connectivity(2, 3)
        # vertex -> geometry node: positional within each cell (first-order geometry)
        c2v = msh.topology.connectivity(3, 0).array.reshape(-1, 8)[: self.n_local_cells]
        vertex_node = np.full(msh.topology.index_map(0).size_local + msh.topology.index_map(0).num_ghosts, -1)
        vertex_node[c2v.reshape(-1)] = self.node_ids[self.geo_dofs.reshape(-1)]
        f2v = msh.topology.connectivity(2, 0)
        boundary = dmesh.exterior_facet_indices(msh.topology)
        on_top = [f for f in boundary if np.all(top[vertex_node[f2v.links(f)]])]
        dofs = fem.locate_dofs_topological(self.V, 2, np.asarray(on_top, dtype=np.int32))
        n_fixed = self.comm.allreduce(len(on_top))
        expected = (keyed.preset.nodes_width - 1) ** 2
        if n_fixed != expected:
            raise RuntimeError(f"fixed face of joint {d.fixed_joint}: found {n_fixed} facets, expected {expected}")
        return fem.dirichletbc(np.zeros(3), dofs, self.V)

    def _fixed_block_bc(self):
        """Clamp every node of the fixed joint block (a built-in end, for the beam reference solutions)."""
        from dolfinx import fem

        block = self.keyed.cell_key[self.cell_ids, 0]
        cells = np.where(block == self.design.fixed_joint)[0].astype(np.int32)
        dofs = fem.locate_dofs_topological(self.V, 3, cells)
        return fem.dirichletbc(np.zeros(3), dofs, self.V)

    # ---------------------------------------------------------------------------------- Newton
    def _make_snes(self):
        from dolfinx.fem.petsc import create_matrix, create_vector
        from petsc4py import PETSc

        s = self.settings
        self.A = self._symmetric_tangent_matrix() if s.linear_solver == "direct" else create_matrix(self.K_form)
        self.r = create_vector(self.R_form)
        snes = PETSc.SNES().create(self.comm)
        snes.setType("newtonls")
        snes.setFunction(self._residual, self.r)
        snes.setJacobian(self._tangent, self.A)
        if self.Pi_form is not None:  # the line search's merit function is the potential energy Pi itself
            snes.setObjective(self._energy)
        snes.setOptionsPrefix(f"morphsim_{id(self)}_")
        self.snes = snes
        self._set_line_search(s.line_search)
        ksp = snes.getKSP()
        if s.linear_solver == "direct":
            # the tangent is the Hessian of Pi (and the Dirichlet rows/columns are zeroed symmetrically):
            # MUMPS LDL^T, ~40 % cheaper than LU here (measured in the bench)
            ksp.setType("preonly")
            ksp.getPC().setType("cholesky")
            ksp.getPC().setFactorSolverType("mumps")
        else:
            ksp.setType("cg")
            ksp.getPC().setType("gamg")
            ksp.setTolerances(rtol=1e-10, max_it=2000)
            self.A.setNearNullSpace(self._rigid_body_modes())
        snes.setConvergenceHistory(length=s.max_it + 1, reset=True)
        self.snes = snes

    def _symmetric_tangent_matrix(self):
        """The tangent's upper triangle in 3 x 3 blocks (PETSc SBAIJ), what MUMPS LDL^T reads: assembly inserts
        half the entries of the full (AIJ) matrix, whose insertion cost as much as the element kernels (session 59,
        16,875 DOFs: assembly 0.142 -> 0.079 s, factorisation 0.108 -> 0.098 s, the same solution). Its sparsity
        is the full matrix's, assembled once at the initial state and converted."""
        from dolfinx.fem.petsc import assemble_matrix, create_matrix
        from petsc4py import PETSc

        full = create_matrix(self.K_form)
        assemble_matrix(full, self.K_form, bcs=self.bcs)
        full.assemble()
        full.setOption(PETSc.Mat.Option.SYMMETRIC, True)  # MatConvert to SBAIJ requires it (values are reset by
        upper = full.convert("sbaij", PETSc.Mat())        # assembly); an output Mat, else petsc4py converts in place
        full.destroy()
        upper.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)  # the element matrices are full
        upper.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)  # the pattern is complete: never grow
        return upper

    def _set_line_search(self, kind: str) -> None:
        from petsc4py import PETSc

        PETSc.Options()[f"{self.snes.getOptionsPrefix()}snes_linesearch_type"] = kind
        self.snes.setFromOptions()

    def _rigid_body_modes(self):
        from dolfinx import la
        from petsc4py import PETSc

        imap, bs = self.V.dofmap.index_map, self.V.dofmap.index_map_bs
        x = self.V.tabulate_dof_coordinates()[: imap.size_local]
        modes = [la.create_petsc_vector(imap, bs) for _ in range(6)]
        arrays = [m.array.reshape(-1, 3) for m in modes]
        for k in range(3):
            arrays[k][:, k] = 1.0
        arrays[3][:, 0], arrays[3][:, 1] = -x[:, 1], x[:, 0]
        arrays[4][:, 0], arrays[4][:, 2] = x[:, 2], -x[:, 0]
        arrays[5][:, 2], arrays[5][:, 1] = x[:, 1], -x[:, 2]
        for i, m in enumerate(modes):  # Gram-Schmidt
            for prev in modes[:i]:
                m.axpy(-m.dot(prev), prev)
            m.normalize()
        return PETSc.NullSpace().create(vectors=modes, comm=self.comm)

    def _residual(self, snes, x, r) -> None:
        from dolfinx.fem.petsc import apply_lifting, assemble_vector, set_bc
        from petsc4py import PETSc

        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.u.vector)
        self.u.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with r.localForm() as r_local:
            r_local.set(0.0)
        assemble_vector(r, self.R_form)
        apply_lifting(r, [self.K_form], bcs=[self.bcs], x0=[x], scale=-1.0)
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        set_bc(r, self.bcs, x, -1.0)

    def _energy(self, snes, x) -> float:
        from dolfinx.fem import assemble_scalar
        from mpi4py import MPI
        from petsc4py import PETSc

        x.copy(self.u.vector)
        self.u.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        return self.comm.allreduce(assemble_scalar(self.Pi_form), op=MPI.SUM)

    def _tangent(self, snes, x, A, P) -> None:
        from dolfinx.fem.petsc import assemble_matrix

        A.zeroEntries()
        assemble_matrix(A, self.K_form, bcs=self.bcs)
        A.assemble()
        self.stats["linear_solves"] += 1

    def load_norm(self) -> float:
        """||R(u = 0, t = 1)||: the full out-of-balance load, the scale of the force tolerance."""
        t_old = self.t.value.copy()
        saved = self.u.vector.copy()
        self.u.vector.set(0.0)
        self.t.value = 1.0
        self._residual(None, self.u.vector, self.r)
        norm = self.r.norm()
        self.t.value = t_old
        saved.copy(self.u.vector)
        return float(norm)

    # ---------------------------------------------------------------------------------- outputs
    def _gather_frame(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Node positions [N, 3] and Cauchy stress [C, Q, 6] in key order on rank 0 (None elsewhere)."""
        self.u1.interpolate(self.u)
        n_owned = self.msh.geometry.index_map().size_local
        v1 = self.V1.dofmap.list.array.reshape(-1, 8)[: self.n_local_cells]
        disp = np.zeros((len(self.node_ids), 3))
        disp[self.geo_dofs.reshape(-1)] = self.u1.x.array.reshape(-1, 3)[v1.reshape(-1)]
        ids, disp = self.node_ids[:n_owned], disp[:n_owned]
        stress = self.stress_expr.eval(np.arange(self.n_local_cells, dtype=np.int32))
        stress = stress.reshape(self.n_local_cells, len(self.quad_points), 6)
        parts = self.comm.gather((ids, disp, self.cell_ids, stress), root=0)
        if self.comm.rank != 0:
            return None
        keyed = self.keyed
        xyz = keyed.node_xyz.copy()
        sig = np.full((keyed.n_cells, len(self.quad_points), 6), np.nan)
        seen_nodes = np.zeros(keyed.n_nodes, dtype=bool)
        for node_id, d, cell_id, s in parts:
            xyz[node_id] += d
            seen_nodes[node_id] = True
            sig[cell_id] = s
        if not seen_nodes.all() or np.isnan(sig).any():
            raise RuntimeError("frame gather missed nodes or cells: key mapping is broken")
        return xyz, sig

    # ---------------------------------------------------------------------------------- stepping
    def run(self, progress=None) -> Frames:
        """Step t from 0 to 1, landing on every frame time; raise SolveFailure on divergence."""
        from petsc4py import PETSc

        s = self.settings
        t_start = time.perf_counter()
        self._make_snes()
        f_ref = self.load_norm()
        atol = max(s.force_tol * f_ref, 1e-12)  # 1 pN floor: above round-off, so an unloaded scene converges
        self.snes.setTolerances(atol=atol, rtol=0.0, stol=0.0, max_it=s.max_it)
        self.stats["load_norm_N"] = f_ref
        frames = Frames(quad_points=self.quad_points, quad_weights=self.quad_weights)
        self._save(frames, 0.0)
        dt_nominal = 1.0 / s.increments
        dt_max = s.save_every * dt_nominal if s.adaptive else dt_nominal
        dt = dt_max
        t_now, increment = 0.0, 0
        u_prev = self.u.vector.copy()  # the last two accepted states before u, for the predictor
        u_prev2 = self.u.vector.copy()
        dt_prev, dt_prev2 = None, None
        x_backup = self.u.vector.copy()
        next_frames = list(s.frame_times[1:])
        while next_frames:
            target = next_frames[0]
            dt = min(dt, target - t_now)
            cut, crossed = 0, False
            while True:
                x_backup.copy(self.u.vector)  # restart from the last converged state (petsc: a.copy(b) is b <- a)
                w1, w2 = predictor_weights(s.predictor, dt, dt_prev, dt_prev2)  # extrapolate along the load path
                if w1:
                    self.u.vector.axpy(w1, u_prev - x_backup)
                if w2:
                    self.u.vector.axpy(w2, u_prev2 - x_backup)
                self.t.value = t_now + dt
                self.snes.solve(None, self.u.vector)
                reason = self.snes.getConvergedReason()
                its = self.snes.getIterationNumber()
                finite = np.isfinite(self.u.vector.norm())
                if reason == -6 and finite:
                    # the energy does not decrease along the Newton step (indefinite tangent far from
                    # equilibrium, or round-off next to it): go on from here with full Newton steps
                    self._set_line_search("basic")
                    self.snes.solve(None, self.u.vector)
                    self._set_line_search(s.line_search)
                    reason = self.snes.getConvergedReason()
                    its += self.snes.getIterationNumber()
                    finite = np.isfinite(self.u.vector.norm())
                    self.stats["line_search_fallbacks"] = self.stats.get("line_search_fallbacks", 0) + 1
                if reason > 0 and finite:
                    break
                history = [float(v) for v in self.snes.getConvergenceHistory()[0][: its + 1]]
                why = SNES_REASONS.get(reason, f"SNES reason {reason}") if finite else "non-finite displacement"
                cut += 1
                self.stats["cutbacks"] += 1
                self.stats["newton_failed"] += its  # spent on an attempt that is thrown away
                if cut > s.max_cutbacks and s.stabilize and s.adaptive:
                    # no equilibrium within reach of the last one: an instability (snap-through); cross it
                    # with damped steps and go on from the undamped equilibrium on the other side
                    x_backup.copy(self.u.vector)
                    log.info("increment at t=%.4g failed %d times (%s); crossing with stabilized steps",
                             t_now + dt, cut, why)
                    try:
                        t_new, its = self._cross_instability(t_now, target, why)
                    except SolveFailure as fail:  # u holds the last damped state accepted
                        self.stats["wall_solve_s"] = time.perf_counter() - t_start
                        raise self._with_last_state(fail, fail.info["t"])
                    dt, crossed = t_new - t_now, True
                    break
                if cut > s.max_cutbacks or not s.adaptive:
                    self.stats["wall_solve_s"] = time.perf_counter() - t_start
                    x_backup.copy(self.u.vector)  # back to the last converged state, for the failure report
                    raise self._with_last_state(SolveFailure(why, t_now + dt, dt, increment, history), t_now)
                log.info("increment at t=%.4g failed (%s); cutting dt %.3g -> %.3g", t_now + dt, why, dt, dt / 2)
                self.snes.getKSP().reset()
                dt /= 2
            increment += 1
            u_prev.copy(u_prev2)
            x_backup.copy(u_prev)
            self.u.vector.copy(x_backup)
            dt_prev2 = None if crossed else dt_prev
            dt_prev = None if crossed else dt  # a jump to another branch is no path to extrapolate
            t_now = t_now + dt
            self.stats["increment_t"].append(t_now)
            self.stats["newton_iterations"].append(its)
            if abs(t_now - target) < 1e-12:
                t_now = target
                next_frames.pop(0)
                self._save(frames, target)
                if progress:
                    progress(target)
            if crossed:
                dt = dt_max / 2 ** (s.max_cutbacks // 2)  # feel the way forward from the new branch
            elif s.adaptive and its <= s.easy_iterations and cut == 0:
                dt = min(dt * s.grow, dt_max)
            elif not s.adaptive:
                dt = dt_nominal
        self.stats["wall_solve_s"] = time.perf_counter() - t_start - self.stats["wall_output_s"]
        self.stats["increments"] = increment
        self.stats["newton_total"] = int(sum(self.stats["newton_iterations"]))
        return frames

    # ------------------------------------------------------------------------- crossing instabilities
    def _use_stabilized(self, on: bool) -> None:
        """Switch the residual and tangent between Pi and Pi + alpha/2 ||u - u_n||^2 (a spring of stiffness
        density alpha tying u to the last accepted state u_n: the backward-Euler step of a viscous medium,
        Abaqus' *STATIC, STABILIZE). Built (JIT) the first time an episode needs it."""
        if on and self._stabilized_forms is None:
            import ufl
            from dolfinx import fem
            from petsc4py import PETSc

            Pi, dx, jit = self._energy_parts
            self.u_n = fem.Function(self.V, name="last_accepted")
            self.alpha = fem.Constant(self.msh, PETSc.ScalarType(0.0))
            spring = 0.5 * self.alpha * ufl.inner(self.u - self.u_n, self.u - self.u_n) * dx
            Pis = Pi + spring
            R = ufl.derivative(Pis, self.u, ufl.TestFunction(self.V))
            K = ufl.derivative(R, self.u, ufl.TrialFunction(self.V))
            self._stabilized_forms = (fem.form(R, jit_params=jit), fem.form(K, jit_params=jit),
                                      fem.form(Pis, jit_params=jit) if self.Pi_form is not None else None)
            self._spring_form = fem.form(2.0 * spring, jit_params=jit)  # alpha ||u - u_n||^2: energy dissipated
        self.R_form, self.K_form, self.Pi_form = self._stabilized_forms if on else self._plain_forms

    def _newton(self) -> tuple[bool, int]:
        """Solve at the current t from the current u; (converged to finite values, Newton iterations)."""
        self.snes.solve(None, self.u.vector)
        ok = self.snes.getConvergedReason() > 0 and np.isfinite(self.u.vector.norm())
        return ok, self.snes.getIterationNumber()

    def _cross_instability(self, t_now: float, target: float, why: str) -> tuple[float, int]:
        """From the equilibrium at t_now, where plain increments find no equilibrium nearby, take damped steps
        (see _use_stabilized) up to `target` (the next frame time), then relax there with damped steps until the
        plain equilibrium Newton finds lies within stabilize_accept_mm of the damped state; return (target,
        Newton iterations). Measured on a sampled all-up 3x3 with 100-145 mm beams: plain increments failed again
        right after every crossing that stopped at the first plain equilibrium (a long, nearly singular stretch,
        not one snap), so a crossing stays damped until the frame time.

        alpha starts at the bending stiffness scale of the design's beams, mu0 h^2 / L^4, and grows x10 when a
        damped step fails, / 2 when one succeeds. Frames are saved only at plain equilibria, so the data stays
        the undamped problem's; the energy the damper dissipated is recorded (stats "stabilized")."""
        from dolfinx.fem import assemble_scalar
        from mpi4py import MPI
        from petsc4py import PETSc

        s = self.settings
        h, L = self.design.thickness, max(self.design.size, 1.0)
        alpha0 = self.material.mu0 * h ** 2 / L ** 4
        alpha, alpha_max = alpha0, alpha0 * 1e8
        dt = (target - t_now) / 8
        t, its_total = t_now, 0
        rec = self.stats.setdefault("stabilized", {"crossings": 0, "steps": 0, "failed_steps": 0,
                                                   "dissipated_mJ": 0.0, "t": []})
        rec["crossings"] += 1
        accepted = self.u.vector.copy()
        for _ in range(s.stabilize_max_steps):
            self._use_stabilized(True)
            accepted.copy(self.u_n.vector)
            self.u_n.x.scatter_forward()
            self.alpha.value = alpha
            step = min(dt, target - t)
            self.t.value = t + step
            ok, its = self._newton()
            its_total += its
            log.debug("damped step t=%.5g alpha=%.3g x alpha0: %s in %d its", t + step, alpha / alpha0,
                     "converged" if ok else "failed", its)
            if not ok:
                rec["failed_steps"] += 1
                accepted.copy(self.u.vector)
                alpha *= 10.0
                if alpha > alpha_max:
                    break
                continue
            rec["steps"] += 1
            rec["dissipated_mJ"] += self.comm.allreduce(assemble_scalar(self._spring_form), op=MPI.SUM)
            t += step
            self.u.vector.copy(accepted)
            alpha = max(alpha / 2.0, alpha0)
            if t < target:
                continue  # plain increments just failed near here: stay damped up to the frame time
            # is there a plain equilibrium here, next to the damped state? (Newton may also converge to a
            # saddle far away; only an equilibrium the damped descent has nearly reached is a stable one)
            self._use_stabilized(False)
            ok, its = self._newton()
            its_total += its
            log.debug("plain Newton at t=%.5g: %s in %d its", t, "converged" if ok else "failed", its)
            if ok:
                jump = (self.u.vector - accepted).norm(PETSc.NormType.NORM_INFINITY)
                log.debug("plain equilibrium %.3g mm from the damped state", jump)
                if jump <= s.stabilize_accept_mm:
                    rec["t"].append([round(t_now, 6), round(t, 6)])
                    log.info("crossed t = %.5g -> %.5g with %d damped steps (%d failed), %.3g mJ dissipated", t_now,
                             t, rec["steps"], rec["failed_steps"], rec["dissipated_mJ"])
                    return t, its_total
                rec["rejected"] = rec.get("rejected", 0) + 1
            accepted.copy(self.u.vector)
        self._use_stabilized(False)
        accepted.copy(self.u.vector)
        raise SolveFailure(f"{why}; stabilized steps from t = {t_now:.5g} found no undamped equilibrium "
                           f"(reached t = {t:.5g}, alpha {alpha / alpha0:.3g} x mu0 h^2 / L^4)", t, dt, 0, [])

    def _with_last_state(self, fail: SolveFailure, t: float) -> SolveFailure:
        """fail with the current displacement's node positions (collective; rank 0 keeps them), so a failure
        report can say how the grid looked where the solve stopped (e.g. its clearance: folding onto itself)."""
        out = self._gather_frame()
        if out is not None and np.isfinite(out[0]).all():
            fail.last_xyz, fail.last_t = out[0], float(t)
        return fail

    def _save(self, frames: Frames, t: float) -> None:
        t0 = time.perf_counter()
        out = self._gather_frame()
        if out is not None:
            xyz, sig = out
            if not (np.isfinite(xyz).all() and np.isfinite(sig).all()):
                raise SolveFailure("non-finite output", t, 0.0, len(self.stats["increment_t"]), [])
            frames.t.append(float(t))
            frames.node_xyz.append(xyz)
            frames.stress.append(sig)
        self.stats["wall_output_s"] += time.perf_counter() - t0


def prestress_for(mesh: KeyedMesh, design: Design, sigma: float, joint_model: str) -> np.ndarray:
    """S0 per cell [C, 3, 3] in key order."""
    return initial_stress(mesh.cell_print_angle, mesh.cell_block < design.n_joints, sigma, joint_model)
