/*
 * clock.c — the clock tree and the chip's time base. See board.h.
 *
 * SYSCLK: HSI16 -> PLL (M = 1, N = 8: VCO 128 MHz, inside 64..344 MHz; R = 2) -> 64 MHz, or with
 * BOARD_HSE_HZ the external clock (M = HSE / 8 MHz, N = 16: the same VCO), with two
 * flash wait states set first (RM0444 "RCC registers": RCC_PLLCFGR, RCC_CR, RCC_CFGR; "FLASH access
 * control register (FLASH_ACR)"; DS13560 "PLL characteristics": fVCO 64..344 MHz, fPLLIN 2.66..16 MHz).
 *
 * Time: TIM2 is a 32-bit counter; prescaled to 1 MHz it wraps every 71.6 minutes, and clock_us
 * extends it to 64 bits (the main loop calls it every few ms). SysTick at 1 kHz only wakes the core
 * from WFI; it counts nothing (a tick lost while interrupts are masked would lose time). The accuracy
 * is HSI16's: ±1 % (DS13560 "Features": internal 16 MHz RC with PLL option, ±1 %), which is why a
 * chip's time_us is a delay since the SYNC (microseconds, not minutes) and the host's SYNC, not this
 * clock, paces the sheet. A UART tolerates it; CAN does not (can.c): build a CAN chip with
 * BOARD_HSE_HZ.
 *
 * TIM2 channel 1 captures the ICM-42688-P's INT1 (data ready) on PA0: the timer latches the count at
 * the edge, so the conversion's instant is exact to the microsecond whatever the main loop is doing.
 */
#include "board.h"

#ifndef BOARD_INT1_RISING
#define BOARD_INT1_RISING 0 /* the part's reset state, which the driver keeps: INT_CONFIG 0x00, INT1 active
                             * low, open drain, pulsed (DS-000347 §14 INT_CONFIG): pull-up on PA0 */
#endif

static uint32_t last;
static uint64_t high;
static uint64_t start;

#if BOARD_HSE_HZ != 0 && (BOARD_HSE_HZ % 8000000u != 0 || BOARD_HSE_HZ > 48000000u)
#error "BOARD_HSE_HZ: a multiple of 8 MHz, 8..48 MHz (the PLL's input is then 8 MHz)"
#endif

#define HSE_SPIN_LIMIT 2000000u /* polls of HSERDY, some 100 ms: a crystal starts in a few ms */

/* The external clock, if any: true when it is ready. */
static bool hse_on(void)
{
#if BOARD_HSE_HZ != 0
    uint32_t n;
    RCC_CR |= (BOARD_HSE_BYPASS ? RCC_CR_HSEBYP : 0u);
    RCC_CR |= RCC_CR_HSEON;
    for (n = 0; n < HSE_SPIN_LIMIT; n++) {
        if ((RCC_CR & RCC_CR_HSERDY) != 0u) {
            return true;
        }
    }
    RCC_CR &= ~RCC_CR_HSEON;
#endif
    return false;
}

static bool pll_64mhz(void)
{
    const bool hse = hse_on();
    RCC_CR = (RCC_CR & ~RCC_CR_HSIDIV_MASK) | RCC_CR_HSION;
    while ((RCC_CR & RCC_CR_HSIRDY) == 0u) {
    }
    RCC_CR &= ~RCC_CR_PLLON;
    while ((RCC_CR & RCC_CR_PLLRDY) != 0u) {
    }
    if (hse) {
        RCC_PLLCFGR = RCC_PLLCFGR_PLLSRC_HSE | ((BOARD_HSE_HZ / 8000000u - 1u) << RCC_PLLCFGR_PLLM_SHIFT) |
                      (16u << RCC_PLLCFGR_PLLN_SHIFT) | (1u << RCC_PLLCFGR_PLLR_SHIFT) | RCC_PLLCFGR_PLLREN;
    } else {
        RCC_PLLCFGR = RCC_PLLCFGR_PLLSRC_HSI16 | (0u << RCC_PLLCFGR_PLLM_SHIFT) | (8u << RCC_PLLCFGR_PLLN_SHIFT) |
                      (1u << RCC_PLLCFGR_PLLR_SHIFT) | RCC_PLLCFGR_PLLREN;
    }
    RCC_CR |= RCC_CR_PLLON;
    while ((RCC_CR & RCC_CR_PLLRDY) == 0u) {
    }
    RCC_AHBENR |= RCC_AHBENR_FLASHEN;
    FLASH_ACR = (FLASH_ACR & ~FLASH_ACR_LATENCY_MASK) | FLASH_ACR_LATENCY_2WS | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN;
    while ((FLASH_ACR & FLASH_ACR_LATENCY_MASK) != FLASH_ACR_LATENCY_2WS) {
    }
    RCC_CFGR = (RCC_CFGR & ~(RCC_CFGR_SW_MASK | RCC_CFGR_HPRE_MASK | RCC_CFGR_PPRE_MASK)) | RCC_CFGR_SW_PLLRCLK;
    while ((RCC_CFGR & RCC_CFGR_SWS_MASK) != RCC_CFGR_SWS_PLLRCLK) {
    }
    return hse || BOARD_HSE_HZ == 0;
}

static uint64_t raw64(void)
{
    const uint32_t now = TIM2_CNT;
    if (now < last) {
        high += (uint64_t)1u << 32;
    }
    last = now;
    return high | now;
}

bool clock_init(void)
{
    const bool ok = pll_64mhz();
    RCC_IOPENR |= RCC_IOPENR_GPIOAEN | RCC_IOPENR_GPIOBEN | RCC_IOPENR_GPIOCEN;
    RCC_APBENR1 |= RCC_APBENR1_TIM2EN;
    TIM2_CR1 = 0u;
    TIM2_PSC = PCLK_HZ / 1000000u - 1u;
    TIM2_ARR = 0xFFFFFFFFu;
    /* INT1 on PA0 (TIM2_CH1, AF2): input capture on TI1, filter 0011 (8 samples at 64 MHz: 125 ns) */
    TIM2_CCMR1 = TIM_CCMR1_CC1S_TI1 | (3u << TIM_CCMR1_IC1F_SHIFT);
    TIM2_CCER = TIM_CCER_CC1E | (BOARD_INT1_RISING ? 0u : TIM_CCER_CC1P);
    GPIO_PUPDR(GPIOA_BASE) = (GPIO_PUPDR(GPIOA_BASE) & ~3u) | (BOARD_INT1_RISING ? 2u : 1u);
    gpio_af(GPIOA_BASE, 0u, 2u);
    TIM2_EGR = TIM_EGR_UG;  /* load the prescaler */
    TIM2_SR = 0u;
    TIM2_CR1 = TIM_CR1_CEN;
    last = TIM2_CNT;
    high = 0u;
    start = last;
    SYST_RVR = SYSCLK_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 0x7u; /* enable, interrupt, processor clock */
    return ok;
}

uint64_t clock_us(void)
{
    return raw64() - start;
}

bool clock_capture(uint64_t *edge_us, uint32_t *missed)
{
    const uint32_t sr = TIM2_SR;
    uint32_t ccr;
    uint64_t now;
    if ((sr & TIM_SR_CC1IF) == 0u) {
        return false;
    }
    ccr = TIM2_CCR1; /* reading CCR1 clears CC1IF */
    if ((sr & TIM_SR_CC1OF) != 0u) {
        (*missed)++;
        TIM2_SR = ~TIM_SR_CC1OF; /* rc_w0: a 0 clears, a 1 leaves the bit */
    }
    now = raw64();
    /* the capture is at most one wrap old (the main loop runs far more often than every 71 minutes) */
    *edge_us = now - (uint32_t)((uint32_t)now - ccr) - start;
    return true;
}

void systick_irq(void) {}
